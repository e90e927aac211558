"""Run under mpirun (2 ranks): NonlinearSolveLayer on a unit square distributed over COMM_WORLD, and
the same layer on the whole mesh on COMM_SELF of rank 0 (the serial reference), forward and backward.
Rank 0 writes both, in DOF-coordinate order, to the .npz file named by argv[1]: keys
``serial/<case>/<quantity>`` and ``split/<case>/<quantity>``, and ``owned_sizes`` of the split mesh.

With ``--inner-caps-differ`` instead: the ranks call a layer whose inner (Krylov) caps differ, as a PRDP
step on per-rank metrics would leave them; every rank must be refused with a ValueError (printed as
``rank R refused: ...``) instead of waiting in different collectives."""
from __future__ import annotations

import sys

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import torch
from gathering import gathered  # tests/mpi, the script's folder

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, forms

CASES = {
    # converged plain Newton (the default snes_type), implicit gradient
    "implicit": (NewtonOptions(rtol=1e-12, atol=1e-14, ksp="lu"), "implicit"),
    # plain Newton capped at 3 steps, each inner CG solve capped at 6 iterations
    "capped-cg": (NewtonOptions(snes_type="newton", max_it=3, ksp=KSPOptions.preset("cg", max_it=6)), "implicit"),
    # the exact derivative of 2 plain Newton steps, warm start included
    "unrolled": (NewtonOptions(snes_type="newton", max_it=2, ksp="lu"), "unrolled"),
}


def run(comm) -> dict:
    msh = dolfinx.mesh.create_unit_square(comm, 12, 12)
    prob = forms.nonlinear_diffusion.problem(msh, controls=("f", "alpha"), g=lambda x: 0.3 * x[0] - 0.2 * x[1] ** 2,
                                             kappa=lambda x: 1.0 + 0.3 * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1]))
    Xf, Xa, X = prob.dof_coordinates("f"), prob.dof_coordinates("alpha"), prob.dof_coordinates()
    out = {}
    for case, (options, diff) in CASES.items():
        inputs = {
            "f": torch.tensor(np.stack([10 + 3 * np.sin(2 * Xf[:, 0] + b) * np.cos(3 * Xf[:, 1]) for b in (0, 1)]),
                              requires_grad=True),
            "alpha": torch.tensor(1.0 + 0.4 * Xa[:, 0] * Xa[:, 1], requires_grad=True),     # shared
        }
        if diff == "unrolled":
            inputs["initial_guess"] = torch.tensor(0.5 * np.sin(np.pi * X[:, 0]) * np.sin(np.pi * X[:, 1]),
                                                   requires_grad=True)
        layer = NonlinearSolveLayer(prob, options, diff=diff)
        u = layer(**inputs)
        weight = torch.tensor(X[:, 0] + 0.5)
        (u * weight).square().sum().backward()
        out[f"{case}/u"] = gathered(comm, X, u.detach().numpy())
        for name, value in inputs.items():
            coords = X if name == "initial_guess" else prob.dof_coordinates(name)
            out[f"{case}/grad_{name}"] = gathered(comm, coords, value.grad.numpy())
        out[f"{case}/newton_steps"] = np.array(layer.stats.newton_steps)
        out[f"{case}/forward_iterations"] = np.array(layer.stats.forward_iterations)
        layer.close()
    out["owned_sizes"] = comm.gather(prob.output_size, root=0)
    return out


def inner_caps_differ() -> None:
    comm = MPI.COMM_WORLD
    prob = forms.nonlinear_diffusion.problem(dolfinx.mesh.create_unit_square(comm, 8, 8), controls=("f",))
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", max_it=2,
                                                    ksp=KSPOptions.preset("cg", max_it=3)))
    layer.inner_max_it = 3 + 2 * comm.rank
    try:
        layer(f=torch.full((prob.control_size("f"),), 10.0, dtype=torch.float64))
        print(f"rank {comm.rank} solved", flush=True)
    except ValueError as err:
        print(f"rank {comm.rank} refused: {err}", flush=True)


def main(path: str) -> None:
    world = MPI.COMM_WORLD
    split = run(world)
    serial = run(MPI.COMM_SELF) if world.rank == 0 else None
    if world.rank == 0:
        results = {"owned_sizes": np.array(split.pop("owned_sizes"))}
        serial.pop("owned_sizes")
        results.update({f"split/{k}": v for k, v in split.items()})
        results.update({f"serial/{k}": v for k, v in serial.items()})
        np.savez(path, **results)


if __name__ == "__main__":
    if sys.argv[1] == "--inner-caps-differ":
        inner_caps_differ()
    else:
        main(sys.argv[1])
