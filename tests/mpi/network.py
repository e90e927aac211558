"""Run under mpirun (any number of ranks): a Newton layer whose conductivity is an MLP kappa_theta(u) at the
quadrature points, solved to convergence with LU. Rank 0 writes the solution and the gradients (the sources'
in DOF-coordinate order, the weights' whole) to the .npz file named by the last argument; with "differ" before
it the ranks hold different weights, and every rank must refuse the call (rank 0 writes the message)."""
from __future__ import annotations

import sys

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import torch
import ufl
from gathering import gathered  # tests/mpi, the script's folder

from fempdl import Network, NewtonOptions, NonlinearProblem, NonlinearSolveLayer
from fempdl.core import _dolfinx


def main(path: str, mode: str) -> None:
    comm = MPI.COMM_WORLD
    torch.manual_seed(3)
    mlp = torch.nn.Sequential(torch.nn.Linear(1, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1),
                              torch.nn.Softplus()).double()
    if mode == "differ":
        with torch.no_grad():
            mlp[0].bias += comm.rank
    msh = dolfinx.mesh.create_unit_square(comm, 10, 10)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, f = dolfinx.fem.Function(V), dolfinx.fem.Function(V)
    v = ufl.TestFunction(V)
    kappa = Network(mlp, (u,), name="kappa", positive=True)
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Constant(msh, 0.0), _dolfinx.boundary_facets(msh))
    prob = NonlinearProblem(ufl.inner(kappa * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx, u, [bc],
                            controls={"f": f})
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
    X = prob.dof_coordinates()
    sources = torch.tensor(np.stack([8 * np.sin(3 * X[:, 0]) * np.cos(2 * X[:, 1]), 6 + 0 * X[:, 0]]),
                           requires_grad=True)
    try:
        out = layer(f=sources)
    except ValueError as err:
        if comm.rank == 0:
            np.savez(path, refused=np.array(str(err)))
        return
    weights = torch.tensor(np.cos(7 * X[:, 0] + 3 * X[:, 1]))
    (out * weights).sum().backward()
    result = {"u": gathered(comm, X, out[0].detach().numpy()), "grad_f": gathered(comm, X, sources.grad[1].numpy()),
              "grad_theta": torch.cat([p.grad.reshape(-1) for p in mlp.parameters()]).numpy()}
    if comm.rank == 0:
        np.savez(path, **result)


if __name__ == "__main__":
    main(sys.argv[-1], sys.argv[1] if len(sys.argv) > 2 else "same")
