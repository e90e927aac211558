"""Your own UFL problem as a layer inside an nn.Module, trained with Adam.

Reaction-diffusion -div(kappa grad u) + c u = f on the L-shape, u = 0 on the boundary. The model holds
log(kappa) as a parameter field and solves the PDE for a batch of sources f; Adam fits kappa so that the
solutions match observations made with a true kappa (converged solves: exact gradients).
"""
import os

from mpi4py import MPI  # noqa: F401  (first: PyPI's DOLFINx finds libmpi once mpi4py has loaded it)
import dolfinx
import torch
import ufl
from petsc4py import PETSc

from fempdl import Problem, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
msh = (mesh.load("lshape", h=0.2) if small else mesh.load("lshape")).mesh      # 116 or 1481 vertices
V = (dolfinx.fem.functionspace(msh, ("Lagrange", 1)) if hasattr(dolfinx.fem, "functionspace")
     else dolfinx.fem.FunctionSpace(msh, ("Lagrange", 1)))
kappa, f, c = dolfinx.fem.Function(V), dolfinx.fem.Function(V), dolfinx.fem.Constant(msh, PETSc.ScalarType(10.0))
u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
a = (kappa * ufl.inner(ufl.grad(u), ufl.grad(v)) + c * u * v) * ufl.dx
L = f * v * ufl.dx
msh.topology.create_connectivity(msh.topology.dim - 1, msh.topology.dim)
boundary = dolfinx.mesh.exterior_facet_indices(msh.topology)
dofs = dolfinx.fem.locate_dofs_topological(V, msh.topology.dim - 1, boundary)
bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V)
problem = Problem(a, L, [bc], controls={"kappa": kappa, "f": f})


class Model(torch.nn.Module):
    def __init__(self, layer, n):
        super().__init__()
        self.layer = layer
        self.log_kappa = torch.nn.Parameter(torch.zeros(n, dtype=torch.float64))

    def forward(self, sources):                               # (B, n) -> (B, n)
        return self.layer(kappa=self.log_kappa.exp(), f=sources)


torch.manual_seed(0)
x = torch.from_numpy(problem.dof_coordinates()[:, :2])
true_kappa = 1.0 + 0.5 * torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1])
sources = torch.randn(8, problem.control_size("f"), dtype=torch.float64)
layer = SolveLayer(problem, KSPOptions.preset("lu"))
with torch.no_grad():
    observed = layer(kappa=true_kappa, f=sources)
model = Model(layer, problem.control_size("kappa"))
optimizer, losses = torch.optim.Adam(model.parameters(), lr=0.05), []
for _step in range(40 if small else 200):
    optimizer.zero_grad()
    loss = ((model(sources) - observed) ** 2).sum() / (observed ** 2).sum()
    loss.backward()
    optimizer.step()
    losses.append(loss.item())
error = ((model.log_kappa.exp() - true_kappa).norm() / true_kappa.norm()).item()
print(f"loss {losses[0]:.3e} -> {losses[-1]:.3e}; kappa error {error:.3e}; solves {layer.stats.forward_solves}")
