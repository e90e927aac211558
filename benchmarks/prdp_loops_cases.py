"""The training loops bench_prdp_loops.py trains, one class per kind of setting, and :func:`build` to pick one.

Each loop holds its data, network, optimiser and capped layer(s) and offers ``epoch()`` (one epoch of
training through the capped solves), ``metric()`` (what PRDP steps on), ``final()`` (the end metric
with converged solves), ``caps`` (what PRDP refines) and ``layers`` (whose statistics are counted).
"""
from __future__ import annotations

import tempfile
from pathlib import Path

from mpi4py import MPI
import dolfinx.fem
import torch
import torch.distributed as dist
import ufl

from fempdl import (
    KSPOptions,
    NewtonOptions,
    NonlinearProblem,
    NonlinearSolveLayer,
    PointObservation,
    Rollout,
    SolveLayer,
    forms,
    mesh,
)
from fempdl.core import _dolfinx
from fempdl.core.meshgen import gmsh, gmsh_session
from fempdl.methods.newton_caps import NewtonCaps


def nmse_sum(u, ref):
    return (((u - ref) ** 2).sum(-1) / (ref ** 2).sum(-1)).sum()


def all_reduce(value: torch.Tensor) -> torch.Tensor:
    if dist.is_available() and dist.is_initialized():
        dist.all_reduce(value)
    return value


class Emulator:
    """A network trained through a layer on a fixed data set: ``readme``, ``warm-linear``,
    ``nonlinear-heat`` and ``ddp`` (``rank``/``size``: this process's shard of every batch)."""

    def __init__(self, setting: str, seed: int, rank: int = 0, size: int = 1):
        self.rank, self.size = rank, size
        msh = (mesh.load("obstacle", MPI.COMM_SELF, h=0.03) if setting == "hole-emulator"
               else mesh.load("lshape", MPI.COMM_SELF, h=0.1))
        data = torch.Generator().manual_seed(0)                    # the data do not depend on the seed
        self.warm = setting != "readme"
        if setting == "readme":
            prob = forms.poisson.problem(msh, controls=("f",))
            basis = torch.randn(8, prob.control_size("f"), dtype=torch.float64, generator=data)
            self.x = torch.randn(80, 8, dtype=torch.float64, generator=data)
            exact = SolveLayer(prob, "lu")
            self.layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
            self.caps, self.key = self.layer, "f"
            with torch.no_grad():
                self.y = exact(f=self.x @ basis)
            width_in = 8
        else:
            if setting == "nonlinear-heat":
                prob = forms.nonlinear_diffusion.problem(msh, controls=("u0",), alpha=20.0, f=0.0, dt=0.01)
                exact = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
                self.layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
                self.caps = NewtonCaps(self.layer, "newton")
            else:
                prob = forms.heat.problem(msh, controls=("u0",), dt=0.002)
                exact = SolveLayer(prob, "lu")
                self.layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
                self.caps = self.layer
            self.key = "u0"
            x = torch.from_numpy(prob.dof_coordinates())
            modes = torch.stack([torch.sin(i * x[:, 0] + 1.0) * torch.cos(j * x[:, 1])
                                 for i in range(1, 4) for j in range(1, 4)], 1)
            self.x = 0.5 * torch.randn(80, 9, dtype=torch.float64, generator=data) @ modes.T
            with torch.no_grad():
                self.u1 = exact(u0=self.x)
                self.y = exact(u0=self.u1, initial_guess=self.u1)
            width_in = prob.output_size
        self.exact, self.layers = exact, [self.layer]
        self.inputs = ({self.key: self.u1[64:], "initial_guess": self.u1[64:]} if self.warm
                       else {self.key: self.x[64:] @ basis})
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(width_in, 64), torch.nn.Tanh(),
                                       torch.nn.Linear(64, prob.output_size)).double()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-2 if setting == "readme" else 3e-3)
        self.order = torch.Generator().manual_seed(seed)

    def predict(self, idx, layer):
        out = self.net(self.x[idx])
        if not self.warm:
            return layer(f=out)
        u1 = self.x[idx] + out                                      # a residual emulator of u0 -> u1
        return layer(u0=u1, initial_guess=u1.detach())

    def epoch(self) -> None:
        for batch in torch.randperm(64, generator=self.order).split(16):
            self.train_step(batch)

    def train_step(self, batch=None) -> None:
        batch = torch.randperm(64, generator=self.order)[:16] if batch is None else batch
        mine = batch[self.rank::self.size]
        self.opt.zero_grad()
        (nmse_sum(self.predict(mine, self.layer), self.y[mine]) / len(batch)).backward()
        for p in self.net.parameters():                        # the batch gradient, on every rank
            all_reduce(p.grad)
        self.opt.step()

    def metric(self, layer=None) -> float:
        mine = torch.arange(64, 80)[self.rank::self.size]
        with torch.no_grad():
            return float(all_reduce(nmse_sum(self.predict(mine, layer or self.layer), self.y[mine]))) / 16

    def final(self) -> dict:
        return {"final_metric": self.metric(self.exact)}


class NewtonInverse:
    """kappa(x) = softplus(MLP(x)) through Newton solves of a regularised p-Laplacian, 4 sources, 40 sensors."""

    def __init__(self, setting: str, seed: int):
        msh = mesh.load("lshape", MPI.COMM_SELF, h=0.07)
        V = _dolfinx.function_space(msh.mesh, "Lagrange", 1)
        u, kappa, f = (dolfinx.fem.Function(V) for _ in range(3))
        v = ufl.TestFunction(V)
        F = (kappa * (1e-4 + ufl.inner(ufl.grad(u), ufl.grad(u))) ** 0.5 * ufl.inner(ufl.grad(u), ufl.grad(v))
             - f * v) * ufl.dx
        bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Function(V), _dolfinx.boundary_facets(msh.mesh))
        prob = NonlinearProblem(F, u, [bc], controls={"kappa": kappa, "f": f})
        coords = torch.from_numpy(prob.dof_coordinates()[:, :2])
        centres = torch.tensor([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5], [0.3, 0.3]], dtype=torch.float64)
        self.f = 10.0 * torch.exp(-((coords[None] - centres[:, None]) ** 2).sum(-1) / 0.1)   # (4, n)
        self.kappa_true = 1.0 + 0.5 * torch.sin(2.0 * coords[:, 0]) * torch.cos(1.5 * coords[:, 1])
        sensors = torch.Generator().manual_seed(0)
        points = coords[torch.randperm(len(coords), generator=sensors)[:40]].numpy()
        self.observe = PointObservation(prob, points)
        self.exact = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))
        with torch.no_grad():
            self.data = self.observe(self.exact(kappa=self.kappa_true, f=self.f))
        self.layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
        self.caps, self.layers, self.coords = NewtonCaps(self.layer, "newton"), [self.layer], coords.float()
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(2, 32), torch.nn.Tanh(), torch.nn.Linear(32, 32),
                                       torch.nn.Tanh(), torch.nn.Linear(32, 1)).double()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=3e-3)
        self.warm, self.state, self.loss = setting == "newton-warm", None, None
        self.inputs = {"kappa": self.kappa().detach(), "f": self.f}

    def kappa(self):
        return torch.nn.functional.softplus(self.net(self.coords.double())).squeeze(-1) + 0.1

    def epoch(self) -> None:
        self.opt.zero_grad()
        start = {"initial_guess": self.state} if self.warm and self.state is not None else {}
        u = self.layer(kappa=self.kappa(), f=self.f, **start)
        loss = ((self.observe(u) - self.data) ** 2).mean() / (self.data ** 2).mean()
        loss.backward()
        self.opt.step()
        self.state, self.loss = u.detach(), loss.item()

    train_step = epoch                     # one optimiser step an epoch

    def metric(self, layer=None) -> float:
        """The misfit of the current kappa (such a loop has no validation set)."""
        start = {"initial_guess": self.state} if self.warm and self.state is not None else {}
        u = (layer or self.layer)(kappa=self.kappa(), f=self.f, **start)
        return float(((self.observe(u) - self.data) ** 2).mean() / (self.data ** 2).mean())

    def final(self) -> dict:
        with torch.no_grad():
            kappa = self.kappa()
            u = self.exact(kappa=kappa, f=self.f)
            loss = float(((self.observe(u) - self.data) ** 2).mean() / (self.data ** 2).mean())
        return {"final_metric": loss,
                "kappa_error": float((kappa - self.kappa_true).norm() / self.kappa_true.norm())}


class NewtonRollout:
    """A source f(x) = MLP(x) fitted to 30 sensors at t = 5, 10, 15, 20 dt of 20 implicit steps of
    u_t = div((1 + u^2) grad u) + f from u = 0 (Newton with LU, each step warm-started from the last state)."""

    def __init__(self, setting: str, seed: int):
        prob = forms.nonlinear_diffusion.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.1), controls=("u0", "f"),
                                                 alpha=1.0, dt=0.05)
        coords = torch.from_numpy(prob.dof_coordinates()[:, :2])
        centres = torch.tensor([[-0.5, -0.5], [0.5, -0.5], [-0.5, 0.5]], dtype=torch.float64)
        f_true = 20.0 * torch.exp(-((coords[None] - centres[:, None]) ** 2).sum(-1) / 0.1).sum(0)
        points = coords[torch.randperm(len(coords), generator=torch.Generator().manual_seed(0))[:30]].numpy()
        self.observe, self.initial = PointObservation(prob, points), torch.zeros(prob.output_size, dtype=torch.float64)
        self.exact = Rollout(NonlinearSolveLayer(prob, NewtonOptions(ksp="lu")), "u0")
        with torch.no_grad():
            self.data = self.observe(self.run(self.exact, f_true))
        self.layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
        self.caps = Rollout(self.layer, "u0")
        self.layers, self.coords = [self.layer], coords
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(2, 32), torch.nn.Tanh(), torch.nn.Linear(32, 1)).double()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-2)

    def source(self):
        return 20.0 * self.net(self.coords).squeeze(-1)

    def run(self, rollout, f):
        return rollout(self.initial, 20, f=f, outputs=[5, 10, 15, 20])       # (4, n): the sensors' times

    def misfit(self, rollout) -> torch.Tensor:
        return ((self.observe(self.run(rollout, self.source())) - self.data) ** 2).mean() / (self.data ** 2).mean()

    def probe(self):
        return self.run(self.caps, self.source().detach())

    def epoch(self) -> None:
        self.opt.zero_grad()
        self.misfit(self.caps).backward()
        self.opt.step()

    train_step = epoch                     # one optimiser step an epoch

    def metric(self) -> float:
        return float(self.misfit(self.caps))

    def final(self) -> dict:
        with torch.no_grad():
            return {"final_metric": float(self.misfit(self.exact))}


class ReadmeLoop:
    """The README's loop as written: 8 amplitudes -> f on the bundled L-shape, -div grad u = f by Richardson +
    Jacobi from zero, 64 training samples in one batch per epoch, 16 validation samples."""

    def __init__(self, setting: str, seed: int):
        prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF), controls=("f",))
        torch.manual_seed(seed)
        basis = torch.randn(8, prob.control_size("f"), dtype=torch.float64)
        self.z_train, self.z_val = torch.randn(64, 8, dtype=torch.float64), torch.randn(16, 8, dtype=torch.float64)
        self.exact = SolveLayer(prob, "lu")
        with torch.no_grad():
            self.u_train, self.u_val = self.exact(f=self.z_train @ basis), self.exact(f=self.z_val @ basis)
        self.layer = self.caps = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
        self.layers, self.inputs = [self.layer], {"f": self.z_val @ basis}
        self.net = torch.nn.Sequential(torch.nn.Linear(8, 64), torch.nn.Tanh(),
                                       torch.nn.Linear(64, prob.output_size)).double()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=1e-2)

    def epoch(self) -> None:
        self.opt.zero_grad()
        (self.layer(f=self.net(self.z_train)) - self.u_train).square().sum(1).mean().backward()
        self.opt.step()

    train_step = epoch                     # one optimiser step an epoch

    def metric(self, layer=None) -> float:
        u = (layer or self.layer)(f=self.net(self.z_val))
        return float(((u - self.u_val).square().sum(1) / self.u_val.square().sum(1)).mean())

    def final(self) -> dict:
        with torch.no_grad():
            return {"final_metric": self.metric(self.exact)}


def plate_with_hole(h: float = 0.042):
    """A user's own gmsh mesh: the unit plate with a hole of radius 0.2 at (0.4, 0.55), written to a .msh
    file and loaded as a user would (``mesh.load(path)``)."""
    path = Path(tempfile.mkdtemp(prefix="plate_")) / "plate.msh"
    with gmsh_session():
        occ = gmsh.model.occ
        plate = occ.cut([(2, occ.addRectangle(0.0, 0.0, 0.0, 1.0, 1.0))], [(2, occ.addDisk(0.4, 0.55, 0.0, 0.2, 0.2))])
        occ.synchronize()
        surface = plate[0][0][1]
        gmsh.model.addPhysicalGroup(2, [surface], 1)
        gmsh.model.addPhysicalGroup(1, [tag for _, tag in gmsh.model.getBoundary([(2, surface)], oriented=False)], 1)
        gmsh.model.setPhysicalName(1, 1, "boundary")
        gmsh.option.setNumber("Mesh.MeshSizeMax", h)
        gmsh.option.setNumber("General.NumThreads", 1)
        gmsh.model.mesh.generate(2)
        gmsh.write(str(path))
    return mesh.load(path, MPI.COMM_SELF)


class PlateEmulator:
    """A new user's emulator on their own gmsh plate with a hole: an MLP maps 9 mode amplitudes to u0, and a
    heat step u0 -> u1 by Richardson + Jacobi from zero, capped at K, advances it; the loss is the nMSE
    against converged steps of the true u0 (64 training samples in batches of 16, 16 for validation)."""

    def __init__(self, setting: str, seed: int):
        prob = forms.heat.problem(plate_with_hole(), controls=("u0",), dt=0.01)
        x = torch.from_numpy(prob.dof_coordinates())
        modes = torch.stack([torch.sin(i * x[:, 0] + 1.0) * torch.cos(j * x[:, 1])
                             for i in range(1, 4) for j in range(1, 4)], 1)            # (n, 9)
        data = torch.Generator().manual_seed(0)
        self.a = torch.randn(80, 9, dtype=torch.float64, generator=data)
        self.exact = SolveLayer(prob, "lu")
        with torch.no_grad():
            self.y = self.exact(u0=self.a @ modes.T)
        self.layer = self.caps = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
        self.layers, self.inputs = [self.layer], {"u0": self.a[64:] @ modes.T}
        torch.manual_seed(seed)
        self.net = torch.nn.Sequential(torch.nn.Linear(9, 64), torch.nn.Tanh(),
                                       torch.nn.Linear(64, prob.output_size)).double()
        self.opt = torch.optim.Adam(self.net.parameters(), lr=3e-3)
        self.order = torch.Generator().manual_seed(seed)

    def train_step(self, batch=None) -> None:
        batch = torch.randperm(64, generator=self.order)[:16] if batch is None else batch
        self.opt.zero_grad()
        (nmse_sum(self.layer(u0=self.net(self.a[batch])), self.y[batch]) / len(batch)).backward()
        self.opt.step()

    def epoch(self) -> None:
        for batch in torch.randperm(64, generator=self.order).split(16):
            self.train_step(batch)

    def metric(self, layer=None) -> float:
        with torch.no_grad():
            return float(nmse_sum((layer or self.layer)(u0=self.net(self.a[64:])), self.y[64:])) / 16

    def final(self) -> dict:
        return {"final_metric": self.metric(self.exact)}


SENSORS = 300


class StokesInverse:
    """An inflow-free Stokes inverse on the channel with a cylinder (Taylor-Hood, h = 0.08): the body force
    f = theta_1 (sin(pi y / H), 0) + theta_2 (0, sin(pi x / L)) + theta_3 (x / L sin(2 pi y / H), 0) fitted
    to the velocity at 300 DOFs (1% noise) by Adam
    (learning rate 0.1 decaying 3% an epoch) to the noise floor; GMRES with the
    Schur-complement fieldsplit ("schur") capped at K, its gradient the implicit one."""

    def __init__(self, setting: str, seed: int):
        msh = mesh.load("obstacle", MPI.COMM_SELF, h=0.08)
        prob = forms.stokes.problem(msh, controls=("f",), velocity={"inlet": 0.0, "walls": 0.0, "obstacle": 0.0})
        xy = torch.from_numpy(prob.field_space("u").tabulate_dof_coordinates()[:, :2])
        x, y = xy[:, 0] / 2.2, xy[:, 1] / 0.41
        self.basis = torch.zeros(3, 2 * len(xy), dtype=torch.float64)      # (3, n_f): (x, y) interleaved
        self.basis[0, 0::2] = torch.sin(torch.pi * y)                      # a push along the channel
        self.basis[1, 1::2] = torch.sin(torch.pi * x)                      # a push across it
        self.basis[2, 0::2] = torch.sin(2 * torch.pi * y) * x              # a shear growing downstream
        self.basis = self.basis[:, :prob.control_size("f")]
        self.theta_true = torch.tensor([2.0, -1.0, 0.5], dtype=torch.float64)
        self.prob, self.exact = prob, SolveLayer(prob, "lu")
        velocity_dofs = len(prob.split(torch.zeros(prob.output_size, dtype=torch.float64))["u"])
        self.sensors = torch.randperm(velocity_dofs, generator=torch.Generator().manual_seed(0))[:SENSORS]
        with torch.no_grad():
            clean = self.observe(self.exact(f=self.theta_true @ self.basis))
        noise = torch.randn(clean.shape, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
        self.data = clean + 0.01 * clean.abs().mean() * noise           # 1% noise: the misfit has a floor
        self.layer = self.caps = SolveLayer(prob, KSPOptions.preset("schur", max_it=1))
        self.layers = [self.layer]
        torch.manual_seed(seed)
        self.theta = torch.nn.Parameter(torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
                                        + 0.1 * torch.randn(3, dtype=torch.float64))
        self.opt = torch.optim.Adam([self.theta], lr=0.1)
        self.decay = torch.optim.lr_scheduler.ExponentialLR(self.opt, gamma=0.97)     # to 1e-3 at 150 epochs
        self.inputs = {"f": (self.theta @ self.basis).detach()}

    def observe(self, x):
        return self.prob.split(x)["u"][..., self.sensors]

    def misfit(self, layer) -> torch.Tensor:
        return ((self.observe(layer(f=self.theta @ self.basis)) - self.data) ** 2).mean() / (self.data ** 2).mean()

    def train_step(self) -> None:
        self.opt.zero_grad()
        self.misfit(self.layer).backward()
        self.opt.step()

    def epoch(self) -> None:
        self.train_step()
        self.decay.step()

    def metric(self) -> float:
        with torch.no_grad():
            return float(self.misfit(self.layer))

    def final(self) -> dict:
        with torch.no_grad():
            return {"final_metric": float(self.misfit(self.exact)),
                    "theta_error": float((self.theta - self.theta_true).norm() / self.theta_true.norm())}


def build(setting: str, seed: int, rank: int = 0, size: int = 1):
    if setting == "readme-as-written":
        return ReadmeLoop(setting, seed)
    if setting == "newton-rollout":
        return NewtonRollout(setting, seed)
    if setting.startswith("plate"):
        return PlateEmulator(setting, seed)
    if setting == "stokes-inverse":
        return StokesInverse(setting, seed)
    if setting.startswith("newton"):
        return NewtonInverse(setting, seed)
    return Emulator("warm-linear" if setting == "ddp" else setting, seed, rank, size)

