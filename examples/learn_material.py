"""A network learns a material field through a nonlinear (Newton) solve.

Nonlinear diffusion -div(kappa(x) (1 + u^2) grad u) = f on the L-shape, u = 0
on the boundary. A small MLP maps coordinates x to log kappa(x); each training
step solves the PDE by Newton for a batch of sources through a
NonlinearSolveLayer (implicit gradients: exact at the converged solution) and
Adam fits the network so that the solutions match observations made with a
true kappa.
"""
import os

from mpi4py import MPI  # noqa: F401  (first: PyPI's DOLFINx finds libmpi once mpi4py has loaded it)
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, forms, mesh

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
msh = mesh.load("lshape", h=0.2) if small else mesh.load("lshape")
problem = forms.nonlinear_diffusion.problem(msh, controls=("kappa", "f"))   # q(u) = 1 + u^2
layer = NonlinearSolveLayer(problem, NewtonOptions(ksp="lu"))              # Newton to rtol 1e-10

torch.manual_seed(0)
x = torch.from_numpy(problem.dof_coordinates("kappa")[:, :2])
true_kappa = 1.0 + 0.5 * torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1])
n_f = problem.control_size("f")
sources = 4.0 + 2.0 * torch.randn(8, n_f, dtype=torch.float64)
with torch.no_grad():
    observed = layer(kappa=true_kappa, f=sources)

net = torch.nn.Sequential(torch.nn.Linear(2, 32), torch.nn.Tanh(), torch.nn.Linear(32, 32), torch.nn.Tanh(),
                          torch.nn.Linear(32, 1)).double()
optimizer, losses = torch.optim.Adam(net.parameters(), lr=0.03), []
for _step in range(80 if small else 300):
    optimizer.zero_grad()
    kappa = net(x).squeeze(-1).exp()
    loss = ((layer(kappa=kappa, f=sources) - observed) ** 2).sum() / (observed ** 2).sum()
    loss.backward()
    optimizer.step()
    losses.append(loss.item())
error = ((net(x).squeeze(-1).exp() - true_kappa).norm() / true_kappa.norm()).item()
stats = layer.stats
print(f"loss {losses[0]:.3e} -> {losses[-1]:.3e}; kappa error {error:.3e}; "
      f"newton steps {stats.newton_steps} in {stats.newton_solves} solves")
