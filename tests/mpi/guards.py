"""Under mpirun -n 2: a distributed-mesh layer or Rollout called differently on the ranks (at other
Constants, steps, batches or caps, with a schedule or without), and PRDP stepped with per-rank
metrics, raise the same ValueError on every rank (instead of one rank waiting in a collective the
other never enters). Writes what each rank caught to OUT.rank<r>.json."""
import json
import sys

from mpi4py import MPI
import torch

from fempdl import PRDP, KSPOptions, NonlinearSolveLayer, Rollout, SolveLayer, forms, mesh

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

heat = forms.heat.problem(problem.V.mesh, controls=("u0", "f"))
step = SolveLayer(heat, "lu")
u0 = torch.ones(heat.output_size, dtype=torch.float64, requires_grad=True)
heat.constants["dt"].value = 0.01 * (1 + comm.rank)                              # Constants differ by rank
try:
    step(u0=u0)
except ValueError as err:
    caught["constants"] = str(err)
heat.constants["dt"].value = 0.01
try:
    Rollout(step, "u0")(u0, 3 + 2 * comm.rank).sum().backward()                    # steps differ by rank
except ValueError as err:
    caught["rollout_steps"] = str(err)
scheduled = Rollout(step, "u0", schedule=("revolve", 2))
try:
    scheduled(u0 if comm.rank == 0 else torch.stack([u0, u0]), 3).sum().backward()   # batches differ by rank
except ValueError as err:
    caught["rollout_batch"] = str(err)
try:
    scheduled(u0, 3, constants={"dt": [0.01, 0.02, 0.01 + 0.01 * comm.rank]}).sum().backward()
except ValueError as err:
    caught["rollout_dt"] = str(err)
capped = Rollout(SolveLayer(heat, KSPOptions.preset("jacobi", max_it=4 + comm.rank)), "u0", schedule="all")
try:
    capped(u0, 3).sum().backward()                                                  # caps differ by rank
except ValueError as err:
    caught["rollout_caps"] = str(err)
scheduled(u0, 3).sum().backward()
caught["rollout_agreed"] = float(u0.grad.abs().max())                              # the same call works

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
