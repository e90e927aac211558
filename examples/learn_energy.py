"""A learned hyperelastic energy psi_theta(F), fitted to a neo-Hookean beam (E = 1, nu = 0.3) through Newton.

psi_theta: an input-convex network of x1 = I_C - 2 - 2 ln J and x2 = (ln J)^2 on the operand F = I + grad u.
The residual is fempdl.derivative of its energy: the stress dpsi/dF and the Jacobian's d2psi/dF2 come from
torch autograd at the quadrature points. Adam fits it to the displacements under three body loads.
"""
import os

from mpi4py import MPI
import dolfinx
import torch
import ufl

from fempdl import Network, NonlinearProblem, NonlinearSolveLayer, derivative, forms

small = os.environ.get("FEMPDL_EXAMPLE_SMALL") == "1"
msh = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [[0.0, 0.0], [4.0, 0.5]], [16, 2] if small else [40, 5])
reference = forms.hyperelasticity.problem(msh, controls=("B",))          # clamped at x = 0


class Energy(torch.nn.Module):
    def __init__(self, width=8):
        super().__init__()
        self.w1, self.b1 = torch.nn.Parameter(0.1 * torch.randn(2, width)), torch.nn.Parameter(torch.zeros(width))
        self.w2, self.log_scale = torch.nn.Parameter(0.1 * torch.randn(width, 1)), torch.nn.Parameter(torch.zeros(()))

    def forward(self, F):                                   # (P, 4): F row by row
        F = F.reshape(-1, 2, 2)                             # J by hand: torch.func's 2nd derivative of det is NaN
        log_J = torch.log(F[:, 0, 0] * F[:, 1, 1] - F[:, 0, 1] * F[:, 1, 0])
        x = torch.stack([(F * F).sum((1, 2)) - 2 - 2 * log_J, log_J ** 2], 1)
        w1, w2 = torch.nn.functional.softplus(self.w1), torch.nn.functional.softplus(self.w2)   # convex in x
        layer = lambda x: torch.nn.functional.softplus(x @ w1 + self.b1) @ w2  # noqa: E731
        return self.log_scale.exp() * (layer(x) - layer(torch.zeros_like(x)))[:, 0]


torch.manual_seed(0)
energy = Energy().double()
u, B, v = dolfinx.fem.Function(reference.V), dolfinx.fem.Function(reference.V), ufl.TestFunction(reference.V)
psi = Network(energy, operands=(ufl.Identity(2) + ufl.grad(u),), name="psi")
F = derivative(psi * ufl.dx, u, v) - ufl.inner(B, v) * ufl.dx
layer = NonlinearSolveLayer(NonlinearProblem(F, u, reference.bcs, controls={"B": B}))
loads = torch.zeros(3, reference.control_size("B"), dtype=torch.float64)
loads[:, 1::2] = torch.tensor([[-1e-4], [-2e-4], [-3e-4]])             # downwards: tip deflections ~ 0.1 to 0.5
with torch.no_grad():
    observed = NonlinearSolveLayer(reference)(B=loads)

epochs = 30 if small else 150
optimizer = torch.optim.Adam(energy.parameters(), lr=0.1)
scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, epochs)
for _ in range(epochs):
    optimizer.zero_grad()
    (loss := ((layer(B=loads) - observed) ** 2).sum() / (observed ** 2).sum()).backward()
    optimizer.step()
    scheduler.step()
F_test = torch.eye(2, dtype=torch.float64) + 0.1 * torch.randn(200, 2, 2, dtype=torch.float64)
J, mu, lmbda = torch.linalg.det(F_test), 1 / 2.6, 0.3 / (1.3 * 0.4)                 # E = 1, nu = 0.3
true = mu / 2 * ((F_test ** 2).sum((1, 2)) - 2 - 2 * J.log()) + lmbda / 2 * J.log() ** 2
error = ((energy(F_test.reshape(-1, 4)) - true).norm() / true.norm()).item()
print(f"loss {loss.item():.2e}; energy error {error:.2e} near F = I; "
      f"newton steps {layer.stats.newton_steps} in {layer.stats.newton_solves} solves")
