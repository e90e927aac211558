"""Half-inverse gradients (HIG): an optimizer that half-inverts the network + physics Jacobian.

For a batch of B samples with outcomes y_i in R^m, J (B m, P) stacks the
Jacobians dy_i/dtheta and g the loss gradients dL/dy_i; with J = U S V^T,

    delta theta = -eta * max(S)^beta * V S^kappa U^T g,

singular values at or below tau * max(S) dropped. kappa = 1, beta = 0 is
gradient descent, kappa = -1 the Gauss-Newton step J^+ g, kappa = -1/2 (the
default) the half-inverse of "Half-Inverse Gradients for Physical Deep
Learning" (Schnell, Holl, Thuerey); beta = -1 - kappa rescales the largest
singular value to one. J_i = J_physics(x_i) J_net(x_i): the network part by
``torch.func``, the physics part by m backward passes (m adjoint solves of a
SolveLayer, batched), or with ``physics_jacobian="jacrev"`` by
``vmap(jacrev(physics))``: one batched forward call and one batched adjoint of
B m right-hand sides. That suits a Newton layer (implicit mode, one custom op
like the linear layer's): its Jacobian J(u)^{-1} dF/dm depends on the state u,
so unlike a linear layer's it is recomputed at every step, and the "rows" way
would repeat the Newton solve m times per sample. :class:`HIG` refuses a J
above ``max_jacobian_bytes``.
"""
from __future__ import annotations

from collections.abc import Callable

import torch
from torch.func import functional_call, jacrev, vmap

__all__ = ["HIG", "half_inverse_update"]


def half_inverse_update(jacobian: torch.Tensor, g: torch.Tensor, *, kappa: float = -0.5, beta: float = 0.0,
                        tau: float = 1e-5, method: str = "auto") -> tuple[torch.Tensor, torch.Tensor, int]:
    """max(S)^beta V S^kappa U^T g for J = U S V^T (shape (R, P), g of length R); S; the rank kept.

    S holds the singular values of J without its zero rows (at most as many as its nonzero rows).

    Singular values <= tau * max(S) are dropped, and so are the ones below
    the method's resolution at any tau: eps max(R, P) max(S) for the SVD.

    ``method``: ``"svd"`` (J's SVD, O(R^2 P) with a large constant),
    ``"gram"`` (the eigendecomposition of the R x R Gram matrix J J^T = U S^2 U^T,
    then V S^kappa U^T g = J^T U S^(kappa - 1) U^T g; cheaper when R < P,
    but it resolves singular values only down to sqrt(eps max(R, P)) max(S),
    about 2e-7 max(S), since squaring loses half the digits) or ``"auto"``
    (gram when R <= P/2 and tau is above that resolution, else svd).
    """
    if jacobian.ndim != 2 or g.shape != jacobian.shape[:1]:
        raise ValueError(f"expected J of shape (R, P) and g of length R, got {tuple(jacobian.shape)} and "
                         f"{tuple(g.shape)}")
    if method not in ("auto", "svd", "gram"):
        raise ValueError(f"method must be 'auto', 'svd' or 'gram', got {method!r}")
    # Outputs no weight moves (a layer's Dirichlet values) give zero rows: they add nothing to U S V^T or
    # to U^T g, and dropping them first makes the decomposition smaller (half the rows on a coarse mesh).
    if not (bool(torch.isfinite(jacobian).all()) and bool(torch.isfinite(g).all())):
        raise ValueError("the Jacobian or the loss gradient holds NaN or inf: the network or the physics "
                         "produced non-finite values; lower the learning rate or check the inputs")
    moving = (jacobian != 0).any(dim=1)
    if not bool(moving.all()):
        jacobian, g = jacobian[moving], g[moving]
    rows, cols = jacobian.shape
    resolution = torch.finfo(jacobian.dtype).eps * max(rows, cols)
    if method == "auto":
        method = "gram" if 2 * rows <= cols and tau > 10 * resolution ** 0.5 else "svd"
    if method == "gram":
        eigenvalues, U = torch.linalg.eigh(jacobian @ jacobian.T)
        S, U = eigenvalues.clamp_min(0).sqrt().flip(0), U.flip(1)                  # descending, like the SVD
        floor = resolution ** 0.5
    else:
        U, S, Vh = torch.linalg.svd(jacobian, full_matrices=False)
        floor = resolution
    largest = S.max() if S.numel() else torch.zeros((), dtype=S.dtype)
    if not largest > 0:
        return torch.zeros(cols, dtype=jacobian.dtype), S, 0
    keep = S > max(tau, floor) * largest
    safe = S.clamp_min(torch.finfo(S.dtype).tiny)
    if method == "gram":
        powered = torch.where(keep, safe ** (kappa - 1.0), torch.zeros_like(S))
        update = jacobian.T @ (U @ (powered * (U.T @ g)))
    else:
        powered = torch.where(keep, safe ** kappa, torch.zeros_like(S))
        update = Vh.T @ (powered * (U.T @ g))
    return largest ** beta * update, S, int(keep.sum())


class HIG:
    """Half-inverse gradient steps on the parameters of ``model`` (module docstring).

    Args:
        model: the network; its trainable parameters are updated in place.
        lr: eta.
        kappa, beta, tau: the exponent, the prefactor exponent and the relative
            truncation of the singular values.
        max_jacobian_bytes: refuse a stacked Jacobian larger than this
            (default 1 GiB).
        method: how J is decomposed, "auto", "svd" or "gram"
            (:func:`half_inverse_update`).

    After a step, ``last_rank`` is the number of singular values kept and
    ``last_singular_values`` all of them (descending).
    """

    def __init__(self, model: torch.nn.Module, lr: float = 1.0, *, kappa: float = -0.5, beta: float = 0.0,
                 tau: float = 1e-5, max_jacobian_bytes: int = 1 << 30, method: str = "auto"):
        if not lr > 0:
            raise ValueError(f"lr must be > 0, got {lr}")
        if not tau >= 0:
            raise ValueError(f"tau must be >= 0, got {tau}")
        self.model, self.lr, self.kappa, self.beta, self.tau = model, float(lr), float(kappa), float(beta), float(tau)
        if method not in ("auto", "svd", "gram"):
            raise ValueError(f"method must be 'auto', 'svd' or 'gram', got {method!r}")
        self.max_jacobian_bytes, self.method = int(max_jacobian_bytes), method
        self.names = [name for name, p in model.named_parameters() if p.requires_grad]
        if not self.names:
            raise ValueError("the model has no trainable parameters")
        self.last_rank = 0
        self.last_singular_values = None
        self._constant_jacobians = {}

    def state_dict(self) -> dict:
        """The settings (HIG keeps no state between steps but the cached linear Jacobians, which are rebuilt)."""
        return {"lr": self.lr, "kappa": self.kappa, "beta": self.beta, "tau": self.tau, "method": self.method}

    def load_state_dict(self, state: dict) -> None:
        self.lr, self.kappa, self.beta, self.tau = state["lr"], state["kappa"], state["beta"], state["tau"]
        self.method = state["method"]

    @property
    def parameters(self) -> list[torch.nn.Parameter]:
        named = dict(self.model.named_parameters())
        return [named[name] for name in self.names]

    def jacobian(self, inputs: torch.Tensor, physics: Callable | None = None,
                 linear_physics: bool = False, physics_jacobian: str = "rows") -> tuple[torch.Tensor, torch.Tensor]:
        """(y, J): outcomes (B, m) and the stacked Jacobian (B m, P) in float64.

        ``linear_physics``: the physics is linear in x (a source or initial state of a
        fixed-matrix layer), so its Jacobian is the same for every sample and step: it
        is computed on the first call and reused (per physics callable).
        ``physics_jacobian``: ``"rows"`` (m backward passes per sample through a batch of
        m copies; any differentiable physics) or ``"jacrev"`` (``vmap(jacrev(physics))``:
        the physics maps one sample (n_x,) to (m,) and composes with torch.func, as
        fempdl's implicit layers do; a nonlinear physics' Jacobian is recomputed every step)."""
        if physics_jacobian not in ("rows", "jacrev"):
            raise ValueError(f"physics_jacobian must be 'rows' or 'jacrev', got {physics_jacobian!r}")
        params = {name: p.detach() for name, p in zip(self.names, self.parameters)}
        n_params = sum(p.numel() for p in params.values())
        with torch.no_grad():
            x = self.model(inputs)
            y = x if physics is None else physics(x)
        batch, m = y.shape
        needed = 8 * batch * (m + x.shape[1]) * n_params
        if needed > self.max_jacobian_bytes:
            raise MemoryError(f"HIG needs a ({batch * m} x {n_params}) Jacobian plus the network's "
                              f"({batch * x.shape[1]} x {n_params}): {needed / 2**20:.1f} MiB, more than "
                              f"max_jacobian_bytes = {self.max_jacobian_bytes / 2**20:.1f} MiB; use a smaller batch, "
                              "fewer outputs or a smaller network, or raise the bound")

        def network(p, sample):
            return functional_call(self.model, p, (sample[None],))[0]

        per_param = vmap(jacrev(network), in_dims=(None, 0))(params, inputs)       # name -> (B, n_x, *shape)
        j_net = torch.cat([per_param[name].reshape(batch, x.shape[1], -1) for name in self.names], dim=2)
        j_net = j_net.double()
        if physics is None:
            return y.double(), j_net.reshape(batch * m, n_params)
        physics_jacobian_of = self._physics_jacobian if physics_jacobian == "rows" else self._physics_jacrev
        if linear_physics:
            if physics not in self._constant_jacobians:
                self._constant_jacobians[physics] = physics_jacobian_of(physics, x[:1], m)[0]
            j_phys = self._constant_jacobians[physics].expand(batch, -1, -1)            # (B, m, n_x)
        else:
            j_phys = physics_jacobian_of(physics, x, m)
        return y.double(), torch.bmm(j_phys, j_net).reshape(batch * m, n_params)

    @staticmethod
    def _physics_jacobian(physics: Callable, x: torch.Tensor, m: int) -> torch.Tensor:
        """(B, m, n_x): per sample, m backward passes (one batched call) with unit output gradients."""
        rows = []
        for sample in x:
            repeated = sample.detach().expand(m, -1).clone().requires_grad_(True)
            with torch.enable_grad():
                out = physics(repeated)
                (grad,) = torch.autograd.grad(out, repeated, grad_outputs=torch.eye(m, dtype=out.dtype))
            rows.append(grad.double())
        return torch.stack(rows)

    @staticmethod
    def _physics_jacrev(physics: Callable, x: torch.Tensor, m: int) -> torch.Tensor:
        """(B, m, n_x) by ``vmap(jacrev(physics))`` at the current x (recomputed at every call)."""
        with torch.enable_grad():
            jac = vmap(jacrev(physics))(x.detach())
        if jac.shape != (x.shape[0], m, x.shape[1]):
            raise ValueError(f"physics_jacobian='jacrev' needs a physics mapping one sample (n_x,) to (m,); its "
                             f"Jacobian has shape {tuple(jac.shape[1:])}, expected {(m, x.shape[1])}")
        return jac.double()

    def step(self, inputs: torch.Tensor, loss_fn: Callable[[torch.Tensor], torch.Tensor],
             physics: Callable | None = None, linear_physics: bool = False, physics_jacobian: str = "rows") -> float:
        """One HIG update for the batch ``inputs``; ``loss_fn(y)`` is the scalar loss of the outcomes
        ``y = physics(model(inputs))`` (B, m). Returns the loss before the update. ``physics_jacobian``:
        how the physics' Jacobian is computed (:meth:`jacobian`)."""
        y, jac = self.jacobian(inputs, physics, linear_physics, physics_jacobian)
        y = y.detach().requires_grad_(True)
        with torch.enable_grad():
            loss = loss_fn(y)
            (g,) = torch.autograd.grad(loss, y)
        update, self.last_singular_values, self.last_rank = half_inverse_update(
            jac, g.reshape(-1), kappa=self.kappa, beta=self.beta, tau=self.tau, method=self.method)
        offset = 0
        with torch.no_grad():
            for p in self.parameters:
                p -= self.lr * update[offset:offset + p.numel()].reshape(p.shape).to(p.dtype)
                offset += p.numel()
        return float(loss.detach())
