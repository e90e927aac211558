"""Under torchrun --nproc_per_node 2 (gloo): data-parallel processes, each with the whole mesh, whose layer
caps drift apart. A training call (gradients on) refuses on every rank; a no-grad call on rank 0 alone (a
validation only rank 0 runs) does not wait for the other rank. A garbage solve on one rank's shard refines
PRDP's cap on both. PRDP stepped on rank 0 alone is refused at the next training call on every rank, without
a hang. Writes what each rank saw to OUT.rank<r>.json."""
import json
import sys

from mpi4py import MPI
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from fempdl import PRDP, KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms, mesh
from fempdl.methods.newton_caps import NewtonCaps

dist.init_process_group("gloo")
rank = dist.get_rank()
msh = mesh.load("lshape", MPI.COMM_SELF, h=0.25)
problem = forms.poisson.problem(msh, controls=("f",))
f = torch.ones(problem.control_size("f"), dtype=torch.float64, requires_grad=True)
seen = {}
layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=5 + rank))          # caps differ by rank
if rank == 0:
    with torch.no_grad():
        seen["rank0_alone"] = float(layer(f=f).abs().max())                          # no collective: returns
try:
    layer(f=f)
except ValueError as err:
    seen["layer"] = str(err)
layer.max_it = 5
seen["agreed"] = float(layer(f=f).sum().item())                                      # the same caps work
newton = NonlinearSolveLayer(forms.nonlinear_diffusion.problem(msh, controls=("f",)))
newton.max_it = 4 + rank
try:
    newton(f=f)
except ValueError as err:
    seen["newton"] = str(err)
# Rank 0's shard is a stiff heat step (plain Newton from zero overshoots), rank 1's a mild one.
heat = forms.nonlinear_diffusion.problem(msh, controls=("u0",), alpha=20.0, f=0.0, dt=0.01)
x = torch.from_numpy(heat.dof_coordinates())
u0 = (2.0 if rank == 0 else 0.01) * torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1])
stepper = NonlinearSolveLayer(heat, NewtonOptions(max_it=1, ksp="lu"))
ctrl = PRDP(NewtonCaps(stepper, "newton"), k0=1, k_cap=20, growth=1.0)    # one Newton step a refinement
stepper(u0=u0.requires_grad_()).sum().backward()
seen["health_k"] = ctrl.k
seen["health_refinements"] = len(ctrl.health_refinements)
# Validating and stepping PRDP on rank 0 alone (a common DDP pattern): the step waits for nobody, and the
# next training call, collective under DDP anyway, refuses on every rank.
layer.max_it = 2
net = DistributedDataParallel(torch.nn.Linear(3, problem.control_size("f")).double())
inputs = torch.ones(3, dtype=torch.float64)
alone = PRDP(layer, k0=2, delta=2, ema_window=1)
seen["ranks"] = repr(alone.ranks)
layer(f=net(inputs)).sum().backward()
if rank == 0:
    alone.step(0.5)
try:
    layer(f=net(inputs)).sum().backward()
except ValueError as err:
    seen["step_alone"] = str(err)
if rank == 1:
    alone.step(0.5)                                                                  # now both have stepped
seen["stepped_together"] = float(layer(f=net(inputs)).sum())
del net
with open(f"{sys.argv[1]}.rank{rank}.json", "w") as fh:
    json.dump(seen, fh)
dist.destroy_process_group()
