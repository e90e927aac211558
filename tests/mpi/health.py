"""Run under mpirun (1 or 2 ranks): PRDP's health check on a mesh distributed over COMM_WORLD. A stiff
heat step (plain Newton from zero overshoots) and a diverging Richardson iteration refine on every rank
alike, since their residual norms are global. Rank 0 writes the caps and the refinements to argv[1] (JSON)."""
from __future__ import annotations

import json
import sys
import warnings

from mpi4py import MPI  # before DOLFINx: the PyPI wheels load MPI through mpi4py
import dolfinx.mesh
import numpy as np
import torch

from fempdl import PRDP, KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms
from fempdl.methods.newton_caps import NewtonCaps

comm = MPI.COMM_WORLD
msh = dolfinx.mesh.create_unit_square(comm, 16, 16)
out = {}
heat = forms.nonlinear_diffusion.problem(msh, controls=("u0",), alpha=20.0, f=0.0, dt=0.01)
x = heat.dof_coordinates()
u0 = torch.tensor(2.0 * np.sin(3 * x[:, 0]) * np.cos(2 * x[:, 1]), requires_grad=True)
stepper = NonlinearSolveLayer(heat, NewtonOptions(max_it=1, ksp="lu"))
newton = PRDP(NewtonCaps(stepper, "newton"), k0=1, k_cap=20, growth=1.0)
stepper(u0=u0).sum().backward()
out["newton"] = newton.health_refinements
poisson = forms.poisson.problem(msh, controls=("f",))
y = poisson.dof_coordinates("f")
f = torch.tensor(1.0 + y[:, 0], requires_grad=True)
layer = SolveLayer(poisson, KSPOptions.preset("jacobi", max_it=8, petsc_options={"ksp_richardson_scale": 1.9}))
linear = PRDP(layer, k0=8, k_cap=50, growth=1.0)        # the residual grows from the seventh step on
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    layer(f=f).sum().backward()
out["linear"] = linear.health_refinements
out["linear_warned"] = any("diverges" in str(w.message) for w in caught)
every = comm.allgather(out)
if comm.rank == 0:
    with open(sys.argv[1], "w") as fh:
        json.dump({"ranks": comm.size, "same_on_every_rank": all(o == out for o in every), **out}, fh)
