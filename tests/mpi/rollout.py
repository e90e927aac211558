"""Run under mpirun (1 or 2 ranks): a Rollout of 4 nonlinear heat steps with a varying dt on a unit square
distributed over COMM_WORLD, as one node (no schedule), by autograd, under two checkpoint schedules and
with the lagged LU ("lu-lagged") inner solve. Rank 0 writes the loss and its directional derivatives along a coordinate
field (for the initial state and the per-step source), summed over the ranks, to argv[1] (JSON)."""
from __future__ import annotations

import json
import sys

from mpi4py import MPI  # before DOLFINx: the PyPI wheels load MPI through mpi4py
import dolfinx.mesh
import numpy as np
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, forms

comm = MPI.COMM_WORLD
msh = dolfinx.mesh.create_unit_square(comm, 12, 12)
problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=2.0, dt=0.01)
step = NonlinearSolveLayer(problem, NewtonOptions(rtol=1e-13, atol=1e-15, ksp="lu"))
x = problem.dof_coordinates()
y = problem.dof_coordinates("f")
u0 = torch.tensor(0.3 * np.sin(3 * x[:, 0]) * x[:, 1], requires_grad=True)
f = torch.tensor(np.stack([1.0 + k * y[:, 0] for k in range(4)]), requires_grad=True)        # (N, n_f)
weights = torch.tensor(1.0 + x[:, 0] * x[:, 1])
lagged = NonlinearSolveLayer(problem, NewtonOptions(rtol=1e-13, atol=1e-15, ksp="lu-lagged"))
total = {}
for schedule in (None, "autograd", ("revolve", 2), ("multistage", 1, 1), "lagged"):
    u0.grad = f.grad = None
    rollout = Rollout(lagged, "u0") if schedule == "lagged" else Rollout(step, "u0", schedule=schedule)
    u = rollout(u0, 4, constants={"dt": [0.01, 0.04, 0.02, 0.03]}, per_step={"f": f}, outputs=[2, 4])
    loss = (weights * u ** 2).sum()
    loss.backward()
    along = {"loss": float(loss), "u0": float((u0.grad * torch.tensor(np.cos(x[:, 0]))).sum()),
             "f": float((f.grad * torch.tensor(np.sin(y[:, 1]))).sum())}
    total.update({f"{key} {schedule}": comm.allreduce(value) for key, value in along.items()})
if comm.rank == 0:
    with open(sys.argv[1], "w") as fh:
        json.dump(total, fh)
