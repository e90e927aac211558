"""Distributed-mesh training under mpirun: one mesh split over the ranks.

Recovers the amplitudes theta of a source f = sum_p theta_p phi_p from the
solution u of -div(grad u) = f on the L-shape, by gradient descent through a
Poisson layer on a mesh distributed over COMM_WORLD. Each rank's tensors hold
its owned DOFs; the layer's forward and adjoint solves are collective. Two
things make the replicated theta train exactly as in a serial run:

* the loss sums over DOFs with ``nmse(..., comm)`` (a differentiable
  allreduce), so every rank computes the same loss;
* each rank's backward reaches theta through its own DOFs only, so the parts
  are summed with ``parallel.sum_gradients`` before the optimizer step.

``fempdl run poisson-inverse-3 --parallel mesh`` does the same for a scene.

    mpirun -n 2 .venv/bin/python scripts/mpi_distributed_mesh.py [--h 0.02] [--steps 40]

Rank 0 prints the loss and the error of theta every 10 steps, and the final
error. (As root, Open MPI also wants OMPI_ALLOW_RUN_AS_ROOT=1 and
OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 in the environment.)
"""
from __future__ import annotations

import argparse

import torch
from mpi4py import MPI

from fempdl import forms, mesh, parallel
from fempdl.bridge_torch import SolveLayer
from fempdl.app.tasks.data import source_modes
from fempdl.ksp_adjoint import KSPOptions
from fempdl.app.training import nmse


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--h", type=float, default=0.02, help="mesh size (0.02: about 9k DOFs)")
    parser.add_argument("--steps", type=int, default=40)
    args = parser.parse_args()
    parallel.abort_on_error()   # an error on one rank ends the job instead of hanging it
    comm = MPI.COMM_WORLD

    problem = forms.poisson.problem(mesh.load("lshape", comm, h=args.h), controls=("f",))
    layer = SolveLayer(problem, KSPOptions.preset("cg", rtol=1e-10))
    theta_ref = torch.tensor([0.6, 1.9, 5.1], dtype=torch.float64)
    modes = torch.as_tensor(source_modes(problem.dof_coordinates(), len(theta_ref), comm))  # (owned DOFs, 3)
    with torch.no_grad():
        u_ref = layer(f=modes @ theta_ref)

    theta = torch.nn.Parameter(torch.full((3,), 3.0, dtype=torch.float64))   # the same on every rank
    optimizer = torch.optim.SGD([theta], lr=3.0)
    for step in range(1, args.steps + 1):
        optimizer.zero_grad()
        loss = nmse(layer(f=modes @ theta), u_ref, comm)
        loss.backward()
        parallel.sum_gradients([theta], comm)
        optimizer.step()
        error = float(((theta - theta_ref).norm() / theta_ref.norm()).detach())
        if comm.rank == 0 and (step % 10 == 0 or step == args.steps):
            print(f"step {step:3d}  loss {loss.item():.3e}  theta error {error:.3e}", flush=True)
    total_dofs = comm.allreduce(problem.output_size)
    if comm.rank == 0:
        print(f"{comm.size} rank(s), {total_dofs} DOFs, {layer.stats.forward_iterations} CG iterations forward "
              f"on rank 0; final theta error {error:.3e}")
    layer.close()


if __name__ == "__main__":
    main()
