"""Data-parallel training in your own loop: every rank solves its share of each batch.

    mpirun -n 2 python examples/data_parallel_loop.py [--epochs 30]

Every rank builds the whole problem (COMM_SELF) and takes its shard of each batch and of the validation
set; gradients are summed over the ranks, the validation (run by PRDP at converged physics) is reduced, and
PRDP (told the ranks) checks they step with the same metric. One process gives the same numbers.
"""
import argparse
import json

from mpi4py import MPI
import numpy as np
import torch

from fempdl import PRDP, KSPOptions, SolveLayer, forms, mesh
from fempdl.core import parallel

parser = argparse.ArgumentParser()
parser.add_argument("--epochs", type=int, default=30)
args = parser.parse_args()
parallel.abort_on_error()                        # an error on one rank ends the job instead of hanging it
comm = MPI.COMM_WORLD
torch.set_num_threads(1)
problem = forms.heat.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.2), controls=("u0",), dt=0.01)
x = problem.dof_coordinates()
modes = torch.from_numpy(np.stack([np.sin(i * x[:, 0] + 1.0) * np.cos(j * x[:, 1])
                                   for i in range(1, 4) for j in range(1, 4)], axis=1))   # (n, 9)
data = torch.Generator().manual_seed(0)            # the same data, network and batches on every rank
a_train, a_val = (torch.randn(m, 9, dtype=torch.float64, generator=data) for m in (32, 8))
u_train, u_val = (SolveLayer(problem)(u0=a @ modes.T) for a in (a_train, a_val))     # converged: the targets
layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=1))
ctrl = PRDP(layer, k0=1, dk=2, delta=2, ema_window=2, k_cap=40, comm=comm)
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Linear(9, 32), torch.nn.Tanh(), torch.nn.Linear(32, problem.output_size)).double()
optimizer, order = torch.optim.Adam(net.parameters(), lr=3e-2), torch.Generator().manual_seed(1)  # same batches


error_sum = lambda u, ref: (((u - ref) ** 2).sum(1) / (ref ** 2).sum(1)).sum()   # noqa: E731


def validate():                                    # the whole validation set's mean, on every rank
    mine = parallel.shard(torch.arange(8), comm)
    return comm.allreduce(error_sum(layer(u0=net(a_val[mine])), u_val[mine]).item()) / 8


for _epoch in range(args.epochs):
    for batch in torch.randperm(32, generator=order).split(8):
        mine = parallel.shard(batch, comm)         # this rank's samples; the loss is the batch mean's share
        optimizer.zero_grad()
        (error_sum(layer(u0=net(a_train[mine])), u_train[mine]) / len(batch)).backward()
        parallel.sum_gradients(net.parameters(), comm)
        optimizer.step()
    ctrl.step(validate)                            # at converged physics, the same on every rank
    parallel.check_same_parameters(net, comm)      # a loop without sum_gradients would drift apart here
done = ctrl.finish(validate)                       # the gap closed at the end; done.metric: the model as judged
iterations = comm.allreduce(layer.stats.total_iterations)
if comm.rank == 0:                                 # one line of JSON: metric, final K, K per epoch, iterations
    print(json.dumps({"metric": done.metric, "k": layer.max_it, "ks": [r.k for r in ctrl.history],
                      "iterations": iterations}))
