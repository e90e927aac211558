"""The learned-conductivity task of bench_network: -div(kappa(u) grad u) = f on a gmsh plate with two holes.

The plate [0, 2] x [0, 1] less two disks of radius 0.2 at (0.6, 0.5) and (1.4, 0.5), P1, u = 0 on every
boundary; the true law kappa(u) = 1 + 4u^2; 8 smooth sources; 50 sensors at random points of the plate.
Three ways to put kappa in the residual F = (kappa grad u, grad v) - (f, v):

* ``"network"``: ``fempdl.Network(mlp, (u,))``, an MLP 1 -> 16 -> 16 -> 1 (softplus), 321 weights;
* ``"ufl_mlp"``: the same MLP written out in UFL, its 321 weights a 321-component DG0 control Function
  (one copy per cell, the gradient summed over the cells), at the same quadrature points;
* ``"polynomial"``: the law c0 + c1 u^2 in torch (a Network), or in UFL with c0, c1 DG0 controls.
"""
from __future__ import annotations

import math
import tempfile
from pathlib import Path

from mpi4py import MPI
import dolfinx
import gmsh
import numpy as np
import torch
import ufl

from fempdl import Network, NonlinearProblem, PointObservation, mesh
from fempdl.core import _dolfinx

WIDTH = 16
N_SOURCES, N_SENSORS = 8, 50
DEGREE = 2          # the quadrature degree UFL gives (1 + 4u^2) grad u . grad v on P1


def plate(h: float, comm=MPI.COMM_WORLD):
    """The plate with two holes meshed by gmsh at size h (rank 0 meshes), as DOLFINx mesh."""
    path = Path(tempfile.mkdtemp()) / "plate.msh" if comm.rank == 0 else None
    if comm.rank == 0:
        gmsh.initialize(["", "-v", "0"])
        gmsh.model.add("plate")
        occ = gmsh.model.occ
        body = occ.addRectangle(0, 0, 0, 2, 1)
        holes = [occ.addDisk(x, 0.5, 0, 0.2, 0.2) for x in (0.6, 1.4)]
        occ.cut([(2, body)], [(2, hole) for hole in holes])
        occ.synchronize()
        surfaces = [tag for _, tag in gmsh.model.getEntities(2)]
        gmsh.model.addPhysicalGroup(2, surfaces, 1)
        gmsh.model.addPhysicalGroup(1, [tag for _, tag in gmsh.model.getEntities(1)], 2)
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("Mesh.MeshSizeMin", h)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
        gmsh.finalize()
    path = comm.bcast(str(path) if path else None, root=0)
    return mesh.load(path, comm).mesh


def mlp(seed: int = 0, width: int = WIDTH) -> torch.nn.Module:
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(1, width), torch.nn.Softplus(), torch.nn.Linear(width, width),
                               torch.nn.Softplus(), torch.nn.Linear(width, 1), torch.nn.Softplus()).double()


class Polynomial(torch.nn.Module):
    """kappa(u) = c0 + c1 u^2 in torch, c = (1, 4): the true law."""

    def __init__(self):
        super().__init__()
        self.c = torch.nn.Parameter(torch.tensor([1.0, 4.0], dtype=torch.float64))

    def forward(self, u):
        return self.c[0] + self.c[1] * u[:, 0] ** 2


def problem(msh, kind: str, module: torch.nn.Module | None = None, width: int = WIDTH):
    """(NonlinearProblem, extra) for ``kind`` (module docstring): extra is the Network, or the DG0 control
    Functions of the UFL variants (``width``: the UFL MLP's)."""
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, f, v = dolfinx.fem.Function(V, name="u"), dolfinx.fem.Function(V, name="f"), ufl.TestFunction(V)
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Constant(msh, 0.0), _dolfinx.boundary_facets(msh))
    dx = ufl.dx(metadata={"quadrature_degree": DEGREE})
    controls, extra = {"f": f}, None
    if kind in ("network", "polynomial"):
        extra = kappa = Network(module, (u,), name="kappa", positive=True, degree=DEGREE)
    elif kind == "ufl_mlp":
        W = dolfinx.fem.Function(_dolfinx.function_space(msh, "DG", 0, shape=(parameter_count(width),)), name="W")
        kappa, controls["W"], extra = ufl_mlp(W, u, width), W, W
    elif kind == "ufl_polynomial":
        DG0 = _dolfinx.function_space(msh, "DG", 0)
        c0, c1 = dolfinx.fem.Function(DG0, name="c0"), dolfinx.fem.Function(DG0, name="c1")
        kappa, extra = c0 + c1 * u ** 2, (c0, c1)
        controls.update(c0=c0, c1=c1)
    else:
        raise ValueError(kind)
    F = ufl.inner(kappa * ufl.grad(u), ufl.grad(v)) * dx - f * v * dx
    return NonlinearProblem(F, u, [bc], controls=controls), extra


def parameter_count(width: int = WIDTH) -> int:
    return 2 * width + width * width + width + width + 1


def ufl_mlp(W, u, width: int = WIDTH):
    """The MLP of :func:`mlp` in UFL, its weights the components of W in torch's parameter order."""
    softplus = lambda z: ufl.ln(1 + ufl.exp(z))  # noqa: E731
    at = iter(range(parameter_count(width)))
    take = lambda n: [W[next(at)] for _ in range(n)]  # noqa: E731
    w1, b1 = take(width), take(width)
    h1 = [softplus(w1[i] * u + b1[i]) for i in range(width)]
    w2, b2 = take(width * width), take(width)
    h2 = [softplus(sum(w2[j * width + i] * h1[i] for i in range(width)) + b2[j]) for j in range(width)]
    w3, b3 = take(width), take(1)
    return softplus(sum(w3[i] * h2[i] for i in range(width)) + b3[0])


def tiled(theta: torch.Tensor, n_cells: int) -> torch.Tensor:
    """The weights as the DG0 control's values: one copy per cell (the gradient sums over the cells)."""
    return theta[None, :].expand(n_cells, theta.numel()).reshape(-1)


def sources(prob, count: int = N_SOURCES) -> torch.Tensor:
    """Smooth sources whose solutions reach u ~ 0.4 to 0.9, where the true law varies 1.6x to 4x."""
    X = prob.dof_coordinates()
    rows = [(20 + 10 * k / count) * (1 + 0.5 * np.sin(math.pi * (k + 1) * X[:, 0] / 2 + k) * np.cos(
        math.pi * X[:, 1] + 0.3 * k)) for k in range(count)]
    return torch.tensor(np.stack(rows), dtype=torch.float64)


def sensors(prob, count: int = N_SENSORS, seed: int = 7) -> PointObservation:
    """``count`` random points of the plate (outside the holes, off the boundary)."""
    rng = np.random.default_rng(seed)
    points = []
    while len(points) < count:
        x, y = rng.uniform([0.05, 0.05], [1.95, 0.95])
        if min(math.hypot(x - cx, y - 0.5) for cx in (0.6, 1.4)) > 0.25:
            points.append((x, y))
    return PointObservation(prob, np.array(points))
