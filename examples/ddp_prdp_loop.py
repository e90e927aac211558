"""PRDP under torchrun + DDP, each process training on its shard of the data (``torchrun --standalone
--nproc_per_node 2 examples/ddp_prdp_loop.py [--epochs 30] [--local-metric]``). Every process holds the whole
problem (MPI.COMM_SELF); the validation, which PRDP runs at converged physics and at the cap, is all-reduced, and
PRDP checks that every rank steps with the same metric, so the ranks refine K together. ``--local-metric`` steps
each rank's own metric, as a first DDP loop often does: PRDP refuses it on every rank. Prints JSON per rank."""
import argparse
import json
import os

from mpi4py import MPI
import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel

from fempdl import PRDP, KSPOptions, SolveLayer, forms, mesh

parser = argparse.ArgumentParser()
parser.add_argument("--epochs", type=int, default=30)
parser.add_argument("--local-metric", action="store_true")
args = parser.parse_args()
dist.init_process_group("gloo")
rank, size = dist.get_rank(), dist.get_world_size()
torch.set_num_threads(1)
problem = forms.heat.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.2), controls=("u0",), dt=0.01)
x, y = problem.dof_coordinates()[:, :2].T               # 9 modes sin(i x + 1) cos(j y), (n, 9)
modes = torch.from_numpy(np.stack([np.sin(i * x + 1) * np.cos(j * y) for i in (1, 2, 3) for j in (1, 2, 3)], 1))
data = torch.Generator().manual_seed(0)                 # one data set; each rank trains on its shard
a_train, a_val = (torch.randn(m, 9, dtype=torch.float64, generator=data) for m in (32, 8))
u_train, u_val = (SolveLayer(problem)(u0=a @ modes.T) for a in (a_train, a_val))     # converged: the targets
layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=1))
ctrl = PRDP(layer, k0=1, delta=2, ema_window=2, k_cap=40)
torch.manual_seed(0)
net = DistributedDataParallel(torch.nn.Sequential(
    torch.nn.Linear(9, 32), torch.nn.Tanh(), torch.nn.Linear(32, problem.output_size)).double())
optimizer, order = torch.optim.Adam(net.parameters(), lr=3e-2), torch.Generator().manual_seed(1)
error_sum = lambda u, ref: (((u - ref) ** 2).sum(1) / (ref ** 2).sum(1)).sum()   # noqa: E731


def validate(model=net.module):                         # this rank's shard; the whole set's mean on every rank
    total = error_sum(layer(u0=model(a_val[rank::size])), u_val[rank::size])
    if not args.local_metric:
        dist.all_reduce(total)
    return total.item() / (len(a_val[rank::size]) if args.local_metric else 8)


try:
    for _epoch in range(args.epochs):
        for batch in torch.randperm(32, generator=order).split(8):
            mine = batch[rank::size]                    # this rank's samples of the batch
            optimizer.zero_grad()
            error_sum(layer(u0=net(a_train[mine])), u_train[mine]).div(len(mine)).backward()   # DDP averages
            optimizer.step()
        ctrl.step(validate)                             # at converged physics and at the cap, on every rank
    line = {"rank": rank, "k": layer.max_it, "ks": [r.k for r in ctrl.history], "metric": ctrl.finish(validate).metric}
except ValueError as err:
    line = {"rank": rank, "error": str(err)}
os.write(1, (json.dumps(line) + "\n").encode())   # one unbuffered write: the ranks share the pipe
del net, optimizer              # DDP's reducer holds the group: freed after it, at exit, the group aborts
dist.destroy_process_group()
