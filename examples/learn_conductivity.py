"""A network inside the weak form learns the law kappa(u) of -div(kappa(u) grad u) = f from 50 sensors.

On a gmsh plate with two holes (u = 0 on its boundary), the MLP kappa_theta(u) is a coefficient of the
residual (fempdl.Network): torch evaluates it, and dkappa/du for the Jacobian, at the quadrature points of
every Newton iteration; the adjoint gives its weights' gradient. The data: 8 solves with kappa = 1 + 4u^2.
"""
import os

from mpi4py import MPI  # noqa: F401  (first: PyPI's DOLFINx finds libmpi once mpi4py has loaded it)
import dolfinx
import gmsh
import numpy as np
import torch
import ufl

from fempdl import Network, NonlinearProblem, NonlinearSolveLayer, PointObservation, forms, mesh

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
gmsh.initialize(["", "-v", "0"])
occ = gmsh.model.occ
occ.cut([(2, occ.addRectangle(0, 0, 0, 2, 1))], [(2, occ.addDisk(x, 0.5, 0, 0.2, 0.2)) for x in (0.6, 1.4)])
occ.synchronize()
gmsh.model.addPhysicalGroup(2, [tag for _, tag in gmsh.model.getEntities(2)], 1)
gmsh.option.setNumber("Mesh.MeshSizeMax", 0.1 if small else 0.05)
gmsh.model.mesh.generate(2)
gmsh.write("plate.msh")
gmsh.finalize()
msh = mesh.load("plate.msh").mesh
truth = forms.nonlinear_diffusion.problem(msh, controls=("f",), alpha=4.0)    # kappa = 1 + 4u^2, u = 0 on the boundary
u, f, v = dolfinx.fem.Function(truth.V), dolfinx.fem.Function(truth.V), ufl.TestFunction(truth.V)
torch.manual_seed(0)
net = torch.nn.Sequential(torch.nn.Linear(1, 16), torch.nn.Softplus(), torch.nn.Linear(16, 16), torch.nn.Softplus(),
                          torch.nn.Linear(16, 1), torch.nn.Softplus()).double()
kappa = Network(net, operands=(u,), name="kappa", positive=True)
problem = NonlinearProblem(ufl.inner(kappa * ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx, u, truth.bcs,
                           controls={"f": f})
layer = NonlinearSolveLayer(problem)                       # Newton to rtol 1e-10; LU inside
x = problem.dof_coordinates()
sources = torch.tensor(np.stack([(20 + k) * (1 + 0.5 * np.sin((k + 1) * x[:, 0] + k) * np.cos(np.pi * x[:, 1]))
                                 for k in range(8)]))
points = [p for p in np.random.default_rng(7).uniform([0.05, 0.05], [1.95, 0.95], (400, 2))
          if min(np.hypot(p[0] - 0.6, p[1] - 0.5), np.hypot(p[0] - 1.4, p[1] - 0.5)) > 0.25][:50]
sensors = PointObservation(problem, np.array(points))
data = sensors(solutions := NonlinearSolveLayer(truth)(f=sources))   # no input requires grad: no graph
optimizer = torch.optim.LBFGS(net.parameters(), max_iter=20 if small else 300, history_size=50,
                              line_search_fn="strong_wolfe", tolerance_grad=1e-14, tolerance_change=1e-16)


def misfit():                                              # one epoch: the 8 Newton solves and their adjoints
    optimizer.zero_grad()
    (loss := ((sensors(layer(f=sources)) - data) ** 2).sum() / (data ** 2).sum()).backward()
    return loss


optimizer.step(misfit)
loss = misfit()
s = torch.linspace(0, float(solutions.max()), 100, dtype=torch.float64)[:, None]
error = ((net(s)[:, 0] - (law := 1 + 4 * s[:, 0] ** 2)).norm() / law.norm()).item()
print(f"loss {loss.item():.2e}; kappa error {error:.2e} over u in [0, {float(solutions.max()):.2f}]; "
      f"network time {kappa.evaluation_time / layer.stats.layer_time:.0%} of the layer's")
