"""K-step iterative solvers as differentiable torch maps (unrolled differentiation).

:func:`solve` runs exactly K iterations from X_0 = 0 for all columns of a
right-hand-side block R (n, B) at once, with torch operations only, so that
autograd through it gives the exact vector-Jacobian product of the K-step
iterate (not of the converged solution). Methods:

* ``"jacobi"`` — Richardson with Jacobi (or no) preconditioning and damping
  omega: X <- X + omega P (R - A X); the iterate of PETSc's KSPRICHARDSON +
  PCJACOBI/PCNONE with ``ksp_richardson_scale`` omega.
* ``"steepest_descent"`` — the PRDP paper's Algorithm 2: r = R - A X,
  alpha = (r.r) / (r.A r), X <- X + alpha r (unpreconditioned).
* ``"cg"`` — preconditioned CG with the recurrences of PETSc's KSPCG, the
  iterate of KSPCG + PCJACOBI/PCNONE.
* ``"gmres"`` — left-preconditioned GMRES(m) with classical Gram-Schmidt and
  restarts, the iterate of KSPGMRES (see :func:`gmres`).

A is a constant :class:`fempdl.sparse.SparseOperator` (or anything with ``@``), P the
inverse diagonal (n, 1) or None.
No 0/0 can occur: when a column's residual vanishes (a zero right-hand side),
or has fallen by 1e-20 from its start (far past double precision), its step
lengths are 0 and the column stays where it is; forward values and gradients
stay finite. Up to that point the iterate is PETSc's.

Memory: autograd keeps ``stored_values`` floats (a few K n B). With
``max_values`` set below that, the iterations run in checkpointed segments of
about sqrt(K) iterations, each recomputed during the backward pass, so about
2 sqrt(K) states are stored instead of K (recomputation is exact: the
iteration is deterministic).
"""
from __future__ import annotations

import math

import torch
from torch.utils.checkpoint import checkpoint

__all__ = ["solve", "METHODS", "stored_values"]


# A column counts as solved once its residual norm has fallen by 1e-20 (far past
# double precision): its step lengths are then 0. Continuing would only push the
# squared norms in the step-length ratios towards underflow, where their
# derivatives (num / den^2) overflow.
_SOLVED = 1e-40


def _safe_ratio(num: torch.Tensor, den: torch.Tensor, solved: torch.Tensor | None = None) -> torch.Tensor:
    """num / den per column, and 0 where den == 0 or the column is ``solved`` (finite gradients)."""
    zero = den == 0 if solved is None else (den == 0) | solved
    return torch.where(zero, torch.zeros_like(num), num / torch.where(zero, torch.ones_like(den), den))


class _Jacobi:
    def init(self, A, P, R, omega):
        return (torch.zeros_like(R),)

    def step(self, A, P, R, omega, state):
        (X,) = state
        return (X + omega * (R - A @ X),)


class _SteepestDescent:
    def init(self, A, P, R, omega):
        return (torch.zeros_like(R), R)

    def step(self, A, P, R, omega, state):
        X, r = state
        Ar = A @ r
        rr = (r * r).sum(0)
        alpha = _safe_ratio(rr, (r * Ar).sum(0), rr <= _SOLVED * (R * R).sum(0).detach())
        return (X + alpha * r, r - alpha * Ar)


class _ConjugateGradient:
    def init(self, A, P, R, omega):
        z = R if P is None else P * R
        beta = (R * z).sum(0)
        # (X, r, z, p, beta); the first step uses p = z.
        return (torch.zeros_like(R), R, z, z, beta)

    def step(self, A, P, R, omega, state):
        X, r, z, p, beta = state
        rr0 = (R * R).sum(0).detach()
        w = A @ p
        a = _safe_ratio(beta, (p * w).sum(0), (r * r).sum(0) <= _SOLVED * rr0)
        X = X + a * p
        r = r - a * w
        z = r if P is None else P * r
        beta_new = (r * z).sum(0)
        p = z + _safe_ratio(beta_new, beta, (r * r).sum(0) <= _SOLVED * rr0) * p
        return (X, r, z, p, beta_new)


METHODS = {"jacobi": _Jacobi(), "steepest_descent": _SteepestDescent(), "cg": _ConjugateGradient()}


def gmres(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int, restart: int) -> torch.Tensor:
    """K iterations of left-preconditioned GMRES(restart) with classical Gram-Schmidt
    (PETSc's KSPGMRES defaults), from X = 0; a cycle cut short by K ends with the
    least-squares update of its partial basis, as PETSc does.

    Happy breakdown (the Krylov space of a column became invariant: the new
    basis vector's norm fell below 1e-14 of the cycle's residual) makes that
    column exact: its later basis vectors are zero and its Hessenberg matrix is
    padded with unit columns on fresh rows, which keeps the small least-squares
    problem of full rank (its padded coefficients are 0) and the gradients finite.
    """
    n, batch = R.shape
    X = torch.zeros_like(R)
    done = 0
    while done < K:
        steps = min(restart, K - done)
        r = R - A @ X
        r = r if P is None else P * r
        beta = r.norm(dim=0)
        broken = beta == 0                                          # nothing left to solve
        basis = [r / torch.where(broken, torch.ones_like(beta), beta)]
        columns = []
        for j in range(steps):
            w = A @ basis[j]
            w = w if P is None else P * w
            # Classical Gram-Schmidt, one basis vector at a time: stacking the
            # basis would give autograd a new (j + 1, n, B) copy to keep per step.
            h = torch.stack([(v * w).sum(0) for v in basis])       # (j + 1, B)
            w = w - sum(v * h[k] for k, v in enumerate(basis))
            h_next = w.norm(dim=0)
            newly = ~broken & (h_next <= 1e-14 * beta)
            pad = broken                                            # broken before this step
            broken = broken | newly
            column = torch.zeros(steps + 1, batch, dtype=R.dtype)
            column = column + torch.nn.functional.pad(torch.where(pad, torch.zeros_like(h), h),
                                                      (0, 0, 0, steps - j))
            unit = torch.zeros(steps + 1, batch, dtype=R.dtype)
            unit[j + 1] = 1.0
            sub = torch.where(broken, torch.zeros_like(h_next), h_next)
            column = column + unit * torch.where(pad, torch.ones_like(sub), sub)
            columns.append(column)
            basis.append(torch.where(broken, torch.zeros_like(w),
                                     w / torch.where(broken, torch.ones_like(h_next), h_next)))
        H = torch.stack(columns, dim=1).permute(2, 0, 1)            # (B, steps + 1, steps)
        rhs = torch.zeros(batch, steps + 1, 1, dtype=R.dtype)
        rhs = rhs + torch.nn.functional.pad(beta[:, None, None], (0, 0, 0, steps))
        Q, T = torch.linalg.qr(H)
        y = torch.linalg.solve_triangular(T, Q.transpose(1, 2) @ rhs, upper=True)[..., 0]   # (B, steps)
        X = X + sum(basis[k] * y[:, k] for k in range(steps))
        done += steps
    return X


# Floats autograd keeps per iteration, in units of n * B, with a constant operator
# and with one whose entries are differentiated (a matrix control), counted
# with saved-tensor hooks. Jacobi with a constant operator keeps nothing: it is
# linear in X, fempdl.sparse.SparseOperator keeps no operand, and its step
# tensor is built once.
_STORED_PER_ITERATION = {"jacobi": (0, 2), "steepest_descent": (2, 2), "cg": (4, 4), "gmres": (4, 5)}


def stored_values(method: str, K: int, n: int, batch: int, *, matrix_grad: bool = False) -> int:
    """Float values autograd keeps for a K-step solve of ``batch`` columns of size n
    (``matrix_grad``: the operator's entries require grad)."""
    if method not in _STORED_PER_ITERATION:
        raise ValueError(f"method must be one of {sorted(_STORED_PER_ITERATION)}, got {method!r}")
    return _STORED_PER_ITERATION[method][int(matrix_grad)] * K * n * batch


def solve(method: str, A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int, *,
          omega: float = 1.0, restart: int = 30, max_values: int | None = None,
          X0: torch.Tensor | None = None) -> torch.Tensor:
    """K iterations of ``method`` on A X = R (R: (n, B)) from X = 0 or from ``X0``; returns X (n, B).

    A warm start is the K-step solve of the residual equation, X0 + S_K(R - A X0),
    which is what PETSc's Krylov methods do with a nonzero initial guess; autograd
    differentiates the dependence on X0 exactly. GMRES is not checkpointed (its
    state is a whole Krylov basis).
    """
    if X0 is not None:
        return X0 + solve(method, A, P, R - A @ X0, K, omega=omega, restart=restart, max_values=max_values)
    if method == "gmres":
        return gmres(A, P, R, K, restart)
    if method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS) + ['gmres']}, got {method!r}")
    impl = METHODS[method]
    if method == "jacobi":
        # One step tensor for all iterations: omega D^{-1}, or omega alone.
        omega = omega if P is None else P * omega
    state = impl.init(A, P, R, omega)

    def run(count, *s):
        for _ in range(count):
            s = impl.step(A, P, R, omega, s)
        return s

    stored = stored_values(method, K, *R.shape, matrix_grad=bool(getattr(A, "requires_grad", False)))
    if max_values is None or not torch.is_grad_enabled() or stored <= max_values:
        return run(K, *state)[0]
    segment = max(1, int(math.sqrt(K)))
    done = 0
    while done < K:
        count = min(segment, K - done)
        state = checkpoint(run, count, *state, use_reentrant=False)
        done += count
    return state[0]
