"""Scale-invariant physics (SIP) training: inverse-physics updates fed back through an L2 proxy loss.

A network predicts x0 from observations; instead of backpropagating
||P(x0) - y*||^2 through the physics P, an inverse update gives
x* = x0 + U(y* | x0), and the network is trained on the proxy loss
1/2 ||x0 - stopgrad(x*)||^2 with any torch optimizer (:func:`sip_step`), as in
"Scale-invariant Learning by Physics Inversion" (Holl, Koltun, Thuerey). The
updates: :class:`GradientStep` (gradient descent: the baseline),
:class:`ExactLinearInverse` (the discrete map's exact inverse, for a control
the right-hand side is affine in; its nonlinear counterpart is
:class:`fempdl.methods.sip_nonlinear.ExactNonlinearInverse`), :class:`GaussNewtonInverse` and
:class:`TikhonovInverse` (damped normal equations, capped CG or SVD), and
:class:`LinearisedGaussNewton` (a nonlinear rollout of layers).

Shapes: x0 is (B, n_x) (the control's DOFs), y* is (B, n_y) (the layer's
output DOFs); every update returns (B, n_x) without a graph.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch

from fempdl.iterative.batched_cg import matrix_free_cg
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.assembly import assemble_scipy

__all__ = ["ExactLinearInverse", "GaussNewtonInverse", "GradientStep", "LinearisedGaussNewton", "TikhonovInverse",
           "proxy_loss", "sip_step"]


def proxy_loss(x0: torch.Tensor, x_star: torch.Tensor) -> torch.Tensor:
    """1/2 ||x0 - stopgrad(x*)||^2 per sample, summed over the (B, n) batch.

    Summed, not averaged: its gradient with respect to x0 is then x0 - x*, the
    inverse update itself, for every sample."""
    return 0.5 * ((x0 - x_star.detach()) ** 2).sum()


def sip_step(model: torch.nn.Module, optimizer, inputs: torch.Tensor, y_target: torch.Tensor,
             inverse) -> tuple[float, torch.Tensor]:
    """One SIP training step: x0 = model(inputs), x* = inverse(x0, y*), a step on the proxy loss.

    Returns the proxy loss and x* (B, n_x)."""
    x0 = model(inputs)
    x_star = inverse(x0.detach(), y_target)
    loss = proxy_loss(x0, x_star)
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss.item(), x_star


class _LayerInverse:
    """Common part: a layer, the control the update acts on, the other inputs held fixed.

    ``free``: the control DOFs an update may change (all but the Dirichlet DOFs
    when the control lives on the solution space)."""

    def __init__(self, layer: SolveLayer, control: str, fixed: dict | None):
        problem = layer.problem
        if control not in problem.control_names:
            raise ValueError(f"unknown control {control!r}; the layer's controls are {list(problem.control_names)}")
        self.layer, self.control, self.fixed = layer, control, dict(fixed or {})
        n = problem.control_size(control)
        on_solution_space = problem.control(control).function_space == problem.V
        self.free = np.setdiff1d(np.arange(n), problem.bc_dofs) if on_solution_space else np.arange(n)

    def physics(self, x: torch.Tensor) -> torch.Tensor:
        return self.layer(**{self.control: x}, **self.fixed)


class GradientStep(_LayerInverse):
    """x* = x0 - eta * d/dx0 [1/2 ||P(x0) - y*||^2] for every sample (one adjoint solve).

    With eta = 1 the proxy gradient equals backpropagation's exactly (Physical
    Gradients for Deep Learning, Theorem 1): the baseline, not a useful inverse."""

    def __init__(self, layer: SolveLayer, control: str, eta: float = 1.0, fixed: dict | None = None):
        super().__init__(layer, control, fixed)
        self.eta = float(eta)

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        x = x0.detach().clone().requires_grad_(True)
        with torch.enable_grad():
            residual = self.physics(x) - y_target
            (grad,) = torch.autograd.grad(0.5 * (residual ** 2).sum(), x)
        return (x0 - self.eta * grad).detach()


class ExactLinearInverse(_LayerInverse):
    """x* = x0 + eta C^{-1} A_full (y* - P(x0)) for a control the right-hand side is affine in.

    For A u = C m + c (Poisson's source: C = M the mass matrix; a heat step's
    initial state: C = M - (1 - theta) dt K) this is the exact inverse of the
    discrete map on the DOFs off the Dirichlet boundary (A_full assembled
    without boundary conditions, both restricted to those rows and columns):
    P(x*) = y* for eta = 1. Values at Dirichlet DOFs are not determined by y*
    and keep x0's. For a heat step C^-1 is the backward heat equation, which
    amplifies high-frequency noise without bound: use a damped inverse there.

    Serial (the operators are assembled into scipy matrices); C is factorised
    once. The matrix must not depend on a control that varies (pass none)."""

    def __init__(self, layer: SolveLayer, control: str, eta: float = 1.0, fixed: dict | None = None):
        super().__init__(layer, control, fixed)
        problem = layer.problem
        if problem.V.mesh.comm.size > 1:
            raise ValueError("ExactLinearInverse assembles serial scipy operators; run it on one process")
        if control not in problem.affine_rhs_controls:
            raise ValueError(f"ExactLinearInverse needs a control the right-hand side is affine in; {control!r} is "
                             f"not (affine: {sorted(problem.affine_rhs_controls)}); use GaussNewtonInverse")
        varying = sorted(set(self.fixed) & problem.matrix_controls)
        if varying:
            raise ValueError(f"ExactLinearInverse assembles the operator once; the matrix depends on {varying}")
        if problem.control(control).function_space != problem.V:
            raise ValueError(f"ExactLinearInverse needs the control on the solution space; {control!r} is not")
        self.eta = float(eta)
        self.operator = assemble_scipy(problem.a_form)[self.free]
        control_matrix = assemble_scipy(problem.rhs_matrix_form(control))[self.free][:, self.free]
        self._solve_control_matrix = spla.factorized(control_matrix.tocsc())

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        with torch.no_grad():
            residual = (y_target - self.physics(x0)).double().numpy()
        step = np.zeros(residual.shape[:1] + (x0.shape[1],))
        step[:, self.free] = np.stack([self._solve_control_matrix(self.operator @ r) for r in residual])
        return (x0 + self.eta * torch.as_tensor(step, dtype=x0.dtype)).detach()


class GaussNewtonInverse(_LayerInverse):
    """x* = x0 + eta dx, dx from ``max_it`` CG iterations on (J^T J + alpha I) dx = J^T (y* - P(x0)).

    J v = P(v) - P(0) and J^T w (one adjoint solve) come from the layer, so the
    control must enter the right-hand side affinely (then P is affine and J
    is exact); ``damping`` = alpha (Tikhonov): along a singular pair s_k of J
    the residual is multiplied by s_k / (s_k^2 + alpha) instead of 1 / s_k, so
    no component grows by more than 1 / (2 sqrt(alpha)). ``max_it`` is the CG
    cap (PRDP may move it), ``rtol`` stops earlier on the normal-equation residual.
    After a call, ``last_iterations`` is the number of CG iterations run.
    """

    def __init__(self, layer: SolveLayer, control: str, *, damping: float = 0.0, max_it: int = 20,
                 rtol: float = 0.0, eta: float = 1.0, fixed: dict | None = None):
        super().__init__(layer, control, fixed)
        if control not in layer.problem.affine_rhs_controls:
            raise ValueError(f"GaussNewtonInverse needs a control the right-hand side is affine in (exact J); "
                             f"{control!r} is not (affine: {sorted(layer.problem.affine_rhs_controls)})")
        if not damping >= 0.0:
            raise ValueError(f"damping must be >= 0, got {damping}")
        if int(max_it) < 1:
            raise ValueError(f"max_it must be >= 1, got {max_it}")
        self.damping, self.max_it, self.rtol, self.eta = float(damping), int(max_it), float(rtol), float(eta)
        self.last_iterations = 0

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        x0d = x0.detach().double()
        # P(0) is the affine part of P; its graph is kept, so every J^T w below is one adjoint solve.
        zero = torch.zeros_like(x0d).requires_grad_(True)
        with torch.enable_grad():
            offset = self.physics(zero)

        def adjoint(w):                                               # J^T w, zero off the free DOFs
            (grad,) = torch.autograd.grad(offset, zero, grad_outputs=w, retain_graph=True)
            out = torch.zeros_like(grad)
            out[:, self.free] = grad[:, self.free]
            return out

        with torch.no_grad():
            def normal(v):                                            # (J^T J + alpha) v
                return adjoint(self.physics(v) - offset) + self.damping * v

            rhs = adjoint(y_target.double() - self.physics(x0d))
            dx, self.last_iterations = matrix_free_cg(normal, rhs, self.max_it, self.rtol)
        return (x0d + self.eta * dx).to(x0.dtype)


class LinearisedGaussNewton:
    """Damped Gauss-Newton steps for a nonlinear differentiable physics P (a rollout of layers).

    One call is one Gauss-Newton step on 1/2 ||P(x) - y*||^2 + beta/2 ||x||^2
    (``prior`` = beta, a Tikhonov prior on x) around x0, damped by alpha
    (``damping``, Levenberg-Marquardt):

        (J^T J + (alpha + beta) I) dx = J^T (y* - P(x0)) - beta x0,    x* = x0 + eta dx,

    J = dP/dx at x0, solved by ``max_it`` CG iterations (:func:`~fempdl.iterative.batched_cg.matrix_free_cg`,
    every sample on its own). J^T w is one backward pass through the kept graph
    of P(x0) (the layers' adjoint solves); J v is the forward difference
    (P(x0 + eps v) - P(x0)) / eps with eps = ``fd_step`` (1 + ||x0||) / ||v||
    per sample (one forward rollout; float64, relative error about fd_step).
    A step therefore costs 1 + k forward and 1 + k backward passes for k CG
    iterations. ``max_it`` is a cap PRDP may move; ``last_iterations`` holds the
    CG iterations of the last call.

    Args:
        physics: x (B, n_x) -> y (B, n_y), differentiable by autograd, samples
            independent (row b of y depends on row b of x only); called as
            ``physics(x, **fixed)`` with the keyword inputs given to the call
            (e.g. each sample's initial marker).
    """

    def __init__(self, physics, *, damping: float = 0.0, prior: float = 0.0, max_it: int = 10, rtol: float = 0.0,
                 eta: float = 1.0, fd_step: float = 1e-6):
        if not callable(physics):
            raise TypeError(f"physics must be a callable x -> y, got {type(physics).__name__}")
        for name, value in (("damping", damping), ("prior", prior)):
            if not value >= 0.0:
                raise ValueError(f"{name} must be >= 0, got {value}")
        if int(max_it) < 1:
            raise ValueError(f"max_it must be >= 1, got {max_it}")
        if not 0.0 < fd_step < 1e-2:
            raise ValueError(f"fd_step must be in (0, 1e-2), got {fd_step}; 1e-6 suits float64")
        self.physics = physics
        self.damping, self.prior, self.max_it, self.rtol = float(damping), float(prior), int(max_it), float(rtol)
        self.eta, self.fd_step = float(eta), float(fd_step)
        self.last_iterations = 0

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor, **fixed) -> torch.Tensor:
        x0d = x0.detach().double().clone().requires_grad_(True)
        with torch.enable_grad():
            y0 = self.physics(x0d, **fixed)
        scale = 1.0 + x0d.detach().norm(dim=-1, keepdim=True)

        def adjoint(w):                                               # J^T w
            (grad,) = torch.autograd.grad(y0, x0d, grad_outputs=w, retain_graph=True)
            return grad

        def tangent(v):                                               # J v by a forward difference
            eps = self.fd_step * scale / v.norm(dim=-1, keepdim=True).clamp_min(1e-300)
            return (self.physics(x0d.detach() + eps * v, **fixed) - y0.detach()) / eps

        x = x0d.detach()
        with torch.no_grad():
            def normal(v):
                return adjoint(tangent(v)) + (self.damping + self.prior) * v

            rhs = adjoint(y_target.double() - y0.detach()) - self.prior * x
            dx, self.last_iterations = matrix_free_cg(normal, rhs, self.max_it, self.rtol)
        return (x + self.eta * dx).to(x0.dtype)


class TikhonovInverse(_LayerInverse):
    """x* = x0 + eta V diag(s / (s^2 + alpha)) U^T (y* - P(x0)), from the SVD J = U S V^T.

    J (n_y, n_free) holds P(e_i) - P(0) for the free control DOFs i (one
    batched forward call; exact because the control enters the right-hand
    side affinely). It is built and decomposed on the first call, so a
    training clock counts it. With ``damping`` = alpha = 0 the update is the
    pseudo-inverse: singular values below n eps s_max are dropped. It is what
    GaussNewtonInverse converges to as its cap grows; J, U and V take
    8 (2 n_y + n_x) n_x bytes, refused above ``max_matrix_bytes``. Serial.
    """

    def __init__(self, layer: SolveLayer, control: str, *, damping: float, eta: float = 1.0,
                 fixed: dict | None = None, max_matrix_bytes: int = 2**30):
        super().__init__(layer, control, fixed)
        problem = layer.problem
        if problem.V.mesh.comm.size > 1:
            raise ValueError("TikhonovInverse decomposes the whole Jacobian on one process; run it serially or "
                             "use GaussNewtonInverse")
        if control not in problem.affine_rhs_controls:
            raise ValueError(f"TikhonovInverse needs a control the right-hand side is affine in (exact J); "
                             f"{control!r} is not (affine: {sorted(problem.affine_rhs_controls)})")
        if not damping >= 0.0:
            raise ValueError(f"damping must be >= 0, got {damping}")
        batched = sorted(name for name, value in self.fixed.items() if torch.as_tensor(value).ndim > 1)
        if batched:
            raise ValueError(f"TikhonovInverse builds one Jacobian for all samples; the fixed inputs {batched} "
                             "have a batch dimension: pass one (n,) tensor each, or use GaussNewtonInverse")
        n_free, n_y = len(self.free), problem.output_size
        needed = 8 * (2 * n_y + n_free) * n_free        # J, then U and V
        if needed > max_matrix_bytes:
            raise MemoryError(f"TikhonovInverse needs a ({n_y} x {n_free}) Jacobian and its SVD: "
                              f"{needed / 2**20:.1f} MiB, more than max_matrix_bytes = "
                              f"{max_matrix_bytes / 2**20:.1f} MiB; use GaussNewtonInverse (matrix-free) or raise "
                              "the bound")
        self.damping, self.eta = float(damping), float(eta)
        self._U = self._filtered_V = None
        self.singular_values: torch.Tensor | None = None

    def _decompose(self) -> None:
        n_x = self.layer.problem.control_size(self.control)
        tangents = torch.zeros(len(self.free) + 1, n_x, dtype=torch.float64)
        tangents[torch.arange(len(self.free)), torch.as_tensor(self.free)] = 1.0     # the last row is x = 0
        with torch.no_grad():
            out = self.physics(tangents)
        jacobian = (out[:-1] - out[-1]).T                                             # (n_y, n_free)
        U, s, Vh = torch.linalg.svd(jacobian, full_matrices=False)
        if self.damping > 0:
            gain = s / (s * s + self.damping)
        else:
            keep = s > max(jacobian.shape) * torch.finfo(s.dtype).eps * s[0]
            gain = torch.where(keep, 1.0 / torch.where(keep, s, 1.0), 0.0)
        self._U, self._filtered_V, self.singular_values = U, Vh.T * gain, s

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        if self._U is None:
            self._decompose()
        x0d = x0.detach().double()
        with torch.no_grad():
            residual = y_target.double() - self.physics(x0d)
            step = torch.zeros_like(x0d)
            step[:, self.free] = (residual @ self._U) @ self._filtered_V.T
        return (x0d + self.eta * step).to(x0.dtype)
