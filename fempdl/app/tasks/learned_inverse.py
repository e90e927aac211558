"""Learning to invert physics: the SIP and HIG scenes, and Adam with backpropagation as their baseline.

A dense network maps an observation y (the layer's output DOFs, n_y) to the
physical input x that produced it (n_x): a Poisson source f from its solution
(y = P(f): -div(kappa grad u) = f, u = 0 on the boundary), the initial
state u0 of one heat step from the state after it, or the source f of
nonlinear diffusion (pde "nonlinear-poisson": -div(kappa (1 + alpha u^2)
grad u) = f, u = 0 on the boundary, solved by Newton to rtol 1e-10 with LU). The truths x are drawn
from the scene's seed: sums of ``modes`` smooth sine modes or of ``modes``
random boxes ("rectangles"), zero at the Dirichlet DOFs; the observations are
the converged (LU) solutions, plus Gaussian noise when ``[data] noise`` > 0.
With ``[data] resample`` the training truths are drawn anew every epoch
(seeded by the epoch, so a resumed run draws the same ones).
The marker PDE (an initial velocity from the marker it moved, a rollout of
flow and marker steps) has its own task class, :mod:`fempdl.app.tasks.marker`, registered under the
same ``sip`` task (:data:`fempdl.app.tasks.SPECS`); :func:`fempdl.app.runs.runner.run_method` and
:mod:`fempdl.app.reports.compare` treat it alike.

Three ways to train the same network (``method``):

* ``"sip"``: the proxy loss 1/2 ||x0 - stopgrad(x*)||^2 (mean over samples)
  with x* from the scene's inverse (:mod:`fempdl.methods.sip`: the exact inverse of
  an affine right-hand side, its Tikhonov-damped version, or damped
  Gauss-Newton CG; for nonlinear-poisson the exact inverse f = M^{-1} N(y),
  N the nonlinear operator's residual at y, which needs no PDE solve),
  stepped by the scene's optimizer;
* ``"hig"``: half-inverse gradient steps (:class:`fempdl.methods.hig.HIG`) on
  L = 1/2 ||P(x0) - y||^2 (mean over samples); a linear physics' Jacobian is
  computed once, a Newton layer's (which depends on the state) at every step
  by ``vmap(jacrev(layer))``: one Newton solve and n_y adjoint solves per sample;
* ``"backprop"``: the baseline, Adam with ``[baseline] lr`` and ``decay`` on
  the same L, its gradient backpropagated through the layer's adjoint.

The validation metric is what the scene's method is judged by: for sip
scenes, the relative error of the inferred x on held-out samples,
||x0 - x||/||x|| over the DOFs off the Dirichlet boundary (y does not
determine x there, and the inverses keep x0's values); for hig scenes, the nMSE of P(x0) against the held-out
observation, ||P(x0) - y||^2 / ||y||^2 (the loss the method minimises). All
tensors are float64: the comparison is about conditioning, not precision.

The task's ``layer`` solves what training does, and only that: its counters are the
training's iterations and Newton steps. The observations (at start and on resampling) and
the validation's solves go through ``reference``, a second layer with the same solve, so
that SIP's exact nonlinear inverse reports no solves and every method's first epoch
counts no data.
"""
from __future__ import annotations

from mpi4py import MPI
import numpy as np
import torch

from fempdl import forms
from fempdl.app.schema import NONLINEAR_PDES, Scene, SipConfig, TaskSpec
from fempdl.app.tasks.base import Task, make_optimizer
from fempdl.app.tasks.data import rectangle_fields, smooth_fields
from fempdl.app.tasks.metrics import sample_nmse
from fempdl.app.tasks.networks import mlp
from fempdl.core import mesh
from fempdl.layer.newton_layer import NonlinearSolveLayer
from fempdl.layer.solve_layer import SolveLayer
from fempdl.methods.hig import HIG
from fempdl.methods.sip import ExactLinearInverse, GaussNewtonInverse, TikhonovInverse, proxy_loss
from fempdl.methods.sip_nonlinear import ExactNonlinearInverse
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.options import KSPOptions

__all__ = ["InversionTask", "method_of"]

#: The sip task on a one-layer physics (poisson, heat); the marker task serves it on the marker rollout.
SIP_SPEC = TaskSpec(name="sip", pdes=("poisson", "heat", "nonlinear-poisson"),
                    required=frozenset({"scene", "mesh", "pde", "sip"}),
                    optional=frozenset({"data", "network", "optimizer", "baseline", "marker"}),
                    unused={"data": frozenset({"k_eps_rtol", "rollout", "train_rollout"})}, trains="method")


def method_of(scene: Scene) -> str:
    """The method a sip or hig scene is about (its baseline is always "backprop")."""
    if scene.task not in ("sip", "hig"):
        raise ValueError(f"scene {scene.name!r} is a {scene.task} scene; methods are compared on sip and hig scenes")
    return scene.task


class InversionTask(Task):
    """A network that infers x from y = P(x), trained by ``method`` (module docstring).

    Shapes: observations (B, n_y) in, inferred inputs (B, n_x) out; the
    network is ``[network] layers`` tanh layers of width ``hidden``.
    """

    specs = (SIP_SPEC, TaskSpec(name="hig", pdes=("poisson", "nonlinear-poisson"),
                                required=frozenset({"scene", "mesh", "pde", "hig"}),
                                optional=frozenset({"data", "network", "optimizer", "baseline"}),
                                unused={"data": frozenset({"k_eps_rtol", "rollout", "train_rollout"}),
                                        "optimizer": frozenset({"type", "lr", "decay"})},
                                trains="method"))

    def __init__(self, scene: Scene, method: str):
        if scene.task not in ("sip", "hig"):
            raise ValueError(f"InversionTask trains sip and hig scenes, not a {scene.task} scene")
        if method not in (scene.task, "backprop"):
            raise ValueError(f"a {scene.task} scene trains with method {scene.task!r} or its baseline 'backprop', "
                             f"got {method!r}")
        self.scene, self.method = scene, method
        pde, data = scene.pde, scene.data
        msh = mesh.load(scene.mesh.name, MPI.COMM_SELF, h=scene.mesh.h)
        self.nonlinear = pde.type in NONLINEAR_PDES
        if pde.type == "poisson":
            self.problem, self.control = forms.poisson.problem(msh, controls=("f",), kappa=pde.kappa,
                                                               degree=pde.degree), "f"
        elif pde.type == "nonlinear-poisson":
            self.problem, self.control = forms.nonlinear_diffusion.problem(
                msh, controls=("f",), kappa=pde.kappa, alpha=pde.alpha, degree=pde.degree), "f"
        else:
            self.problem, self.control = forms.heat.problem(msh, controls=("u0",), dt=pde.dt, theta=pde.theta,
                                                            kappa=pde.kappa, degree=pde.degree), "u0"
        self.free = np.setdiff1d(np.arange(self.problem.output_size), self.problem.bc_dofs)
        # Training's solves on layer (counted), the data's and validation's on reference: the same solve.
        self.layer, self.reference = self._converged_layer(), self._converged_layer()
        self.layers = [self.layer]
        self.train_size, self.val_size = data.train, data.validation
        self.x_val, self.y_val = self._samples(data.validation, np.random.default_rng([data.seed, 1]))
        self.x_train, self.y_train = self._samples(data.train, np.random.default_rng([data.seed, 0]))
        torch.manual_seed(data.seed)
        n_x, n_y = self.problem.control_size(self.control), self.problem.output_size
        self.model = mlp(n_y, n_x, scene.network.hidden, scene.network.layers, torch.nn.Tanh).double()
        self.scheduler = None
        if method == "backprop":
            self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), "adam",
                                                            scene.baseline.lr, scene.baseline.decay)
        elif method == "sip":
            self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                            scene.optimizer.lr, scene.optimizer.decay)
            self.inverse = self._inverse(scene.sip)
        else:
            h = scene.hig
            self.optimizer = HIG(self.model, lr=h.lr, kappa=h.kappa, beta=h.beta, tau=h.tau,
                                 method=h.method, max_jacobian_bytes=int(h.max_jacobian_mib * 2**20))

    def _converged_layer(self):
        """LU, or for a nonlinear PDE converged plain Newton (full steps, LU, rtol 1e-10) from zero."""
        if self.nonlinear:
            return NonlinearSolveLayer(self.problem, NewtonOptions(ksp="lu"))
        return SolveLayer(self.problem, KSPOptions.preset("lu"))

    # ------------------------------------------------------------ data
    def _samples(self, count: int, rng: np.random.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` truths x (zero at the Dirichlet DOFs) and their observations y = P(x) (+ noise)."""
        draw = smooth_fields if self.scene.data.truths == "smooth" else rectangle_fields
        x = torch.as_tensor(draw(self.problem.dof_coordinates(), count, self.scene.data.modes, rng))
        x[:, self.problem.bc_dofs] = 0.0                    # f and u0 live on the solution space
        with torch.no_grad():
            y = self.reference(**{self.control: x})
        noise = self.scene.data.noise
        if noise > 0:
            scatter = torch.as_tensor(rng.standard_normal(tuple(y.shape)))
            scatter[:, self.problem.bc_dofs] = 0.0         # the boundary values are known exactly
            y = y + noise * y.abs().max() * scatter
        return x, y

    def start_epoch(self, epoch: int) -> None:
        """With ``[data] resample``: new training truths, seeded by the epoch (the same on a resumed run)."""
        if self.scene.data.resample:
            rng = np.random.default_rng([self.scene.data.seed, 2, epoch])
            self.x_train, self.y_train = self._samples(self.train_size, rng)

    # ------------------------------------------------------------ methods
    def _inverse(self, spec: SipConfig):
        if self.nonlinear:          # the scene allows the exact inverse only
            return ExactNonlinearInverse(self.layer, self.control, eta=spec.eta)
        if spec.inverse == "exact":
            return ExactLinearInverse(self.layer, self.control, eta=spec.eta)
        if spec.inverse == "tikhonov":
            return TikhonovInverse(self.layer, self.control, damping=spec.damping, eta=spec.eta)
        return GaussNewtonInverse(self.layer, self.control, damping=spec.damping, max_it=spec.cg_iterations,
                                  eta=spec.eta)

    def physics(self, x: torch.Tensor) -> torch.Tensor:
        return self.layer(**{self.control: x})

    def loss(self, idx) -> torch.Tensor:
        """The method's training loss on the samples ``idx``, a mean over them."""
        y = self.y_train[idx]
        x0 = self.model(y)
        if self.method == "sip":
            return proxy_loss(x0, self.inverse(x0.detach(), y)) / len(idx)
        return self._physics_loss(self.physics(x0), y)

    @staticmethod
    def _physics_loss(u: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        return 0.5 * ((u - y) ** 2).sum(-1).mean()

    def train_step(self, idx) -> float:
        if self.method != "hig":
            return super().train_step(idx)
        y = self.y_train[idx]
        if self.nonlinear:          # the Jacobian of a Newton solve changes with the state: every step
            return self.optimizer.step(y, lambda u: self._physics_loss(u, y), physics=self.physics,
                                       physics_jacobian="jacrev")
        return self.optimizer.step(y, lambda u: self._physics_loss(u, y), physics=self.physics,
                                   linear_physics=True)

    def validation_errors(self, idx) -> torch.Tensor:
        x0 = self.model(self.y_val[idx])
        if self.scene.task == "sip":
            error, truth = (x0 - self.x_val[idx])[:, self.free], self.x_val[idx][:, self.free]
            return error.norm(dim=-1) / truth.norm(dim=-1)
        return sample_nmse(self.reference(**{self.control: x0}), self.y_val[idx])

    def close(self) -> None:
        self.layer.close()
        self.reference.close()
