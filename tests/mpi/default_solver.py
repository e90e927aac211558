"""Run under mpirun (any number of ranks): the iterative defaults of a layer without options on a
distributed 3D mesh, with the direct limits set below it: CG + AMG for Poisson, GMRES + ILU(0) (block
Jacobi) inside Newton for nonlinear diffusion. Rank 0 writes the solutions, gradients and the options'
types in DOF-coordinate order to the .npz file named by argv[1]."""
from __future__ import annotations

import sys

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import torch
from gathering import gathered  # tests/mpi, the script's folder

from fempdl import NonlinearSolveLayer, SolveLayer, forms
from fempdl.solve import default_solver


def main(path: str) -> None:
    comm = MPI.COMM_WORLD
    default_solver.DIRECT_MAX_DOFS = default_solver.DIRECT_MAX_DOFS_REFACTORED = {1: 10, 2: 10, 3: 10}
    msh = dolfinx.mesh.create_unit_cube(comm, 6, 6, 6)
    out = {}
    for pde, prob, layer_type in (("poisson", forms.poisson.problem(msh, controls=("f", "kappa")), SolveLayer),
                                  ("newton", forms.nonlinear_diffusion.problem(msh), NonlinearSolveLayer)):
        layer = layer_type(prob)
        ksp = layer.options if layer_type is SolveLayer else layer.options.ksp
        out[f"{pde}/ksp"] = np.array(f"{ksp.ksp_type}+{ksp.pc_type}")
        inputs = {}
        for name in prob.control_names:
            X = prob.dof_coordinates(name)
            inputs[name] = torch.tensor(np.sin(2 * X[:, 0]) * np.cos(X[:, 1] + X[:, 2]) + 1.5, requires_grad=True)
        u = layer(**inputs)
        u.square().sum().backward()
        out[f"{pde}/u"] = gathered(comm, prob.dof_coordinates(), u.detach().numpy())
        for name, value in inputs.items():
            out[f"{pde}/grad_{name}"] = gathered(comm, prob.dof_coordinates(name), value.grad.numpy())
        layer.close()
    if comm.rank == 0:
        np.savez(path, **out)


if __name__ == "__main__":
    main(sys.argv[1])
