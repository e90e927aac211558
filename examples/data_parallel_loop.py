"""Data-parallel training in your own loop: every rank solves its share of each batch.

    mpirun -n 2 python examples/data_parallel_loop.py [--epochs 30] [--out result.json]

Every rank builds the whole (small) problem on its own process (``COMM_SELF``),
takes its shard of every mini-batch and of the validation set
(``parallel.shard``), and before each optimizer step the gradients are summed
over the ranks (``parallel.sum_gradients``), so every rank takes the same step
as one process would on the whole batch. The loss of a shard is a sum over its
samples divided by the whole batch's size, so the summed gradient is the batch
mean's. The validation metric is reduced over the ranks before PRDP sees it,
and PRDP is told the ranks (``comm=``): it checks that they all step with the
same metric, since a rank that refined K alone would train on with another cap.
Run on one process it gives the same numbers (to float rounding).
(As root, Open MPI also wants OMPI_ALLOW_RUN_AS_ROOT=1 and OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1.)
"""
import argparse
import json

import numpy as np
import torch
from mpi4py import MPI

from fempdl import PRDP, KSPOptions, SolveLayer, forms, mesh
from fempdl.core import parallel

parser = argparse.ArgumentParser()
parser.add_argument("--epochs", type=int, default=30)
parser.add_argument("--out", help="write the final metrics as JSON (rank 0)")
args = parser.parse_args()
parallel.abort_on_error()                        # an error on one rank ends the job instead of hanging it
comm = MPI.COMM_WORLD
torch.set_num_threads(1)

problem = forms.heat.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.2), controls=("u0",), dt=0.01)
x = problem.dof_coordinates()
modes = torch.from_numpy(np.stack([np.sin(i * x[:, 0] + 1.0) * np.cos(j * x[:, 1])
                                   for i in range(1, 4) for j in range(1, 4)], axis=1))   # (n, 9)
data = torch.Generator().manual_seed(0)            # the same data and network on every rank
a_train = torch.randn(32, 9, dtype=torch.float64, generator=data)
a_val = torch.randn(8, 9, dtype=torch.float64, generator=data)
with torch.no_grad():
    reference = SolveLayer(problem)                # no options: the converged solution
    u_train, u_val = reference(u0=a_train @ modes.T), reference(u0=a_val @ modes.T)

layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=1))
ctrl = PRDP(layer, k0=1, dk=2, delta=2, ema_window=2, k_cap=40, comm=comm)
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Linear(9, 32), torch.nn.Tanh(), torch.nn.Linear(32, problem.output_size)).double()
optimizer = torch.optim.Adam(net.parameters(), lr=3e-2)
order = torch.Generator().manual_seed(1)           # the same batches on every rank


def error_sum(u, ref):
    """Sum over the samples of ||u_i - ref_i||^2 / ||ref_i||^2."""
    return (((u - ref) ** 2).sum(1) / (ref ** 2).sum(1)).sum()


for epoch in range(args.epochs):
    for batch in torch.randperm(32, generator=order).split(8):
        mine = parallel.shard(batch, comm)         # this rank's samples of the batch
        optimizer.zero_grad()
        loss = error_sum(layer(u0=net(a_train[mine])), u_train[mine]) / len(batch)
        loss.backward()
        parallel.sum_gradients(net.parameters(), comm)
        optimizer.step()
    with torch.no_grad():
        mine = parallel.shard(torch.arange(8), comm)
        metric = comm.allreduce(error_sum(layer(u0=net(a_val[mine])), u_val[mine]).item()) / 8
    ctrl.step(metric)

iterations = comm.allreduce(layer.stats.total_iterations)
if comm.rank == 0:
    print(f"{comm.size} rank(s): validation nMSE {metric:.6e}, K {layer.max_it}, solver iterations {iterations}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"metric": metric, "k": layer.max_it, "iterations": iterations,
                       "history": [rec.k for rec in ctrl.history]}, fh)
