"""Under mpirun -n 2: a distributed-mesh layer called differently on the ranks, and PRDP stepped with
per-rank metrics, raise the same ValueError on every rank (instead of one rank waiting in a collective
the other never enters). Writes what each rank caught to OUT.rank<r>.json."""
import json
import sys

from mpi4py import MPI
import torch

from fempdl import PRDP, KSPOptions, NonlinearSolveLayer, SolveLayer, forms, mesh

comm = MPI.COMM_WORLD
problem = forms.poisson.problem(mesh.load("lshape", comm, h=0.2), controls=("f",))
f = torch.ones(problem.control_size("f"), dtype=torch.float64)
caught = {}

layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=5 + comm.rank))     # caps differ by rank
try:
    layer(f=f)
except ValueError as err:
    caught["cap"] = str(err)
layer.max_it = 5
try:
    layer(f=f if comm.rank == 0 else torch.stack([f, f]))                          # batches differ by rank
except ValueError as err:
    caught["batch"] = str(err)
try:
    layer(f=f if comm.rank == 0 else f.float())                                    # dtypes differ by rank
except ValueError as err:
    caught["dtype"] = str(err)
try:
    layer(f=f.clone().requires_grad_(comm.rank == 0))                              # a backward on one rank
except ValueError as err:
    caught["grad"] = str(err)
caught["agreed"] = float(layer(f=f).abs().max())                                   # the same call works

newton = NonlinearSolveLayer(forms.nonlinear_diffusion.problem(problem.V.mesh, controls=("f",)))
try:
    newton(f=f if comm.rank == 0 else f.float())
except ValueError as err:
    caught["newton_dtype"] = str(err)

ctrl = PRDP(layer, k0=2, delta=2, ema_window=1)
assert ctrl.comm.size == comm.size            # the mesh's communicator, taken from the layer
try:
    ctrl.step(0.5 + comm.rank)                                                     # per-rank metrics
except ValueError as err:
    caught["prdp"] = str(err)
ctrl.step(0.5)                                                                     # the same metric works
caught["k"] = layer.max_it
with open(f"{sys.argv[1]}.rank{comm.rank}.json", "w") as fh:
    json.dump(caught, fh)
