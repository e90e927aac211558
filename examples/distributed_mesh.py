"""A mesh split over MPI ranks: recover source amplitudes through a distributed Poisson layer.

    mpirun -n 2 python examples/distributed_mesh.py [--h 0.02] [--steps 40]

f = sum_p theta_p phi_p; gradient descent on theta through the layer on a mesh
distributed over COMM_WORLD. Tensors hold each rank's owned DOFs and the solves
are collective. The loss sums over all ranks (``parallel.allreduce_sum``, a
differentiable allreduce), and each rank's gradient, reaching theta through
its own DOFs only, is summed before the step (``parallel.sum_gradients``), so
theta trains exactly as in a serial run. (As root, Open MPI also wants
OMPI_ALLOW_RUN_AS_ROOT=1 and OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1.)
"""
import argparse

from mpi4py import MPI
import numpy as np
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import parallel
from fempdl.ksp_adjoint import KSPOptions

parser = argparse.ArgumentParser()
parser.add_argument("--h", type=float, default=0.02)
parser.add_argument("--steps", type=int, default=40)
args = parser.parse_args()
parallel.abort_on_error()                       # an error on one rank ends the job instead of hanging it
comm = MPI.COMM_WORLD

problem = forms.poisson.problem(mesh.load("lshape", comm, h=args.h), controls=("f",))
layer = SolveLayer(problem, KSPOptions.preset("cg", rtol=1e-10))
modes = torch.as_tensor(np.stack([problem.interpolate(lambda x, p=p: np.sin(p * np.pi * (x[0] + 1) / 2)
                                                      * np.sin(p * np.pi * (x[1] + 1) / 2), "f")
                                  for p in (1, 2, 3)], axis=1))       # (owned DOFs, 3)
theta_ref = torch.tensor([0.6, 1.9, 5.1], dtype=torch.float64)
with torch.no_grad():
    u_ref = layer(f=modes @ theta_ref)
ref_norm = parallel.allreduce_sum((u_ref ** 2).sum(), comm)

theta = torch.nn.Parameter(torch.full((3,), 3.0, dtype=torch.float64))    # the same on every rank
optimizer = torch.optim.SGD([theta], lr=3.0)
for _step in range(1, args.steps + 1):
    optimizer.zero_grad()
    loss = parallel.allreduce_sum(((layer(f=modes @ theta) - u_ref) ** 2).sum(), comm) / ref_norm
    loss.backward()
    parallel.sum_gradients([theta], comm)
    optimizer.step()
    parallel.check_same_parameters([theta], comm)   # without sum_gradients each rank would fit its own theta
error = float((theta - theta_ref).norm() / theta_ref.norm())
dofs = comm.allreduce(problem.output_size)      # collective: every rank calls it
if comm.rank == 0:
    print(f"{comm.size} rank(s), {dofs} DOFs, loss {loss.item():.3e}; "
          f"final theta error {error:.3e}")
layer.close()
