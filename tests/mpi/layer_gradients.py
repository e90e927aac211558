"""Run under mpirun (any number of ranks): Poisson and heat layers on a mesh
distributed over COMM_WORLD, forward and backward; rank 0 writes the solutions
and gradients in DOF-coordinate order to the .npz file named by argv[1]."""
from __future__ import annotations

import sys

from mpi4py import MPI
import numpy as np
import torch
from gathering import gathered  # tests/mpi, the script's folder

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

SOLVERS = {"lu": KSPOptions.preset("lu"), "jacobi": KSPOptions.preset("jacobi", max_it=30),
           "cg": KSPOptions.preset("cg", rtol=1e-12), "gmres": KSPOptions.preset("gmres", max_it=12)}
PROBLEMS = {"poisson": (forms.poisson.problem, ("f", "kappa"), {}),
            "heat": (forms.heat.problem, ("u0", "f", "kappa"), {"dt": 0.01, "theta": 0.5})}


def main(path: str) -> None:
    comm = MPI.COMM_WORLD
    msh = mesh.load("lshape", comm, h=0.1)
    out = {}
    for pde, (build, controls, kwargs) in PROBLEMS.items():
        prob = build(msh, controls=controls, **kwargs)
        inputs = {}
        for i, name in enumerate(controls):
            X = prob.dof_coordinates(name)
            rows = [np.sin((i + 2) * X[:, 0] + b) * np.cos(2 * X[:, 1]) + 1.5 for b in range(2)]
            inputs[name] = torch.tensor(np.stack(rows) if name != "kappa" else rows[0], requires_grad=True)
        weight = torch.tensor(prob.dof_coordinates()[:, 0] + 0.5)
        for solver, options in SOLVERS.items():
            layer = SolveLayer(prob, options)
            u = layer(**inputs)
            (u * weight).square().sum().backward()
            out[f"{pde}/{solver}/u"] = gathered(comm, prob.dof_coordinates(), u.detach().numpy())
            for name, value in inputs.items():
                out[f"{pde}/{solver}/grad_{name}"] = gathered(comm, prob.dof_coordinates(name), value.grad.numpy())
                value.grad = None
            out[f"{pde}/{solver}/forward_iterations"] = np.array(layer.stats.forward_iterations)
            layer.close()
    sizes = comm.gather(prob.output_size, root=0)
    if comm.rank == 0:
        np.savez(path, owned_sizes=np.array(sizes), **out)


if __name__ == "__main__":
    main(sys.argv[1])
