"""Under mpirun: fields of a distributed mesh to Functions and XDMF.

Writes JSON (rank 0) with, per check, the largest error over all ranks: the
owned-DOF round trip to_function -> from_function, and the P1 nodal values
(owned and ghost) of a linear field after to_function's ghost update and the
interpolation XDMF output uses; and the XDMF file's global node count.
"""
import json
import sys
from pathlib import Path

from mpi4py import MPI
import numpy as np

from fempdl import forms, mesh
from fempdl.core import io

comm = MPI.COMM_WORLD
out = Path(sys.argv[1])
msh = mesh.load("lshape", comm, h=0.2)
poisson = forms.poisson.problem(msh, controls=("f",), degree=2)
stokes = forms.stokes.problem(msh)
rng = np.random.default_rng(comm.rank)
errors = {}


def linear(x):
    return 1.0 + 2.0 * x[0] - 3.0 * x[1]


for label, prob, names in (("poisson", poisson, (None, "f")), ("stokes", stokes, (None, "u", "p"))):
    for name in names:
        space = prob.function_space(name)
        n = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
        x = rng.standard_normal(n)
        errors[f"{label}/{name}/round_trip"] = float(np.abs(prob.from_function(prob.to_function(x, name), name) - x)
                                                     .max(initial=0.0))
u = poisson.interpolate(linear)                       # owned values only
nodal = io.nodal_field(poisson.to_function(u), "u")   # P1: uses the ghosts of the P2 field
xy = nodal.function_space.tabulate_dof_coordinates()
errors["poisson/p1_nodes_with_ghosts"] = float(np.abs(nodal.x.array - linear(xy.T)).max())
path = io.write_fields(out / "poisson.xdmf", poisson, {"u": u, "f": poisson.interpolate(linear, "f")})
worst = {key: comm.allreduce(value, op=MPI.MAX) for key, value in errors.items()}
ghosts = comm.allreduce(nodal.function_space.dofmap.index_map.num_ghosts, op=MPI.SUM)
if comm.rank == 0:
    text = path.read_text()
    nodes = int(text.split('<Geometry GeometryType="XY">')[1].split('Dimensions="')[1].split()[0])
    json.dump({"errors": worst, "ghosts": ghosts, "nodes": nodes,
               "vertices": msh.mesh.topology.index_map(0).size_global}, open(out / "result.json", "w"))
