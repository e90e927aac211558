"""Preconditioned CG on (n, B) blocks, in place and without autograd: KSPCG's recurrences for every
column at once, either for K steps (:func:`capped_cg`, :func:`fast_cg`) or until each column meets
its own tolerance (:func:`converged_cg`).

Preconditioner P: the inverse diagonal (n, 1) (PCJACOBI) or ``None``. One iteration is one sparse
product, the column products p.w and r.z (and z.z for a tolerance) as multiply-then-sum passes
through a scratch block, and the updates of X, r, z and p. (A dense X^T Y product per column
pair reads each block once but runs far slower inside MKL's gemm on tiny values and with a second
thread busy; the multiply-then-sum kernels do not.) The sums run in another order than PETSc's,
so iterates agree with KSPCG's to round-off, not bit for bit.

A pure cap stops a column before K only where KSPCG with NORM_NONE would (:func:`capped_cg`): on
an exactly zero r.z or p.Ap, a sign change, or a NaN. Past convergence CG's recursive residual
keeps shrinking until r.z underflows to 0, a few hundred iterations on, and a huge cap ends there.
The last of those iterations run on subnormal numbers, whose rounding depends on the order of the
sums: PETSc's own counts differ from build to build there, and some of its columns go on into NaN.
This CG stops a column at the first subnormal r.z instead (CONVERGED_ATOL, the reason PETSc gives
at r.z == 0): a few percent fewer iterations than PETSc, the same iterate to round-off.

Stopping to a tolerance follows KSPCG with the preconditioned norm and KSPConvergedDefault, column
by column: dp_k = ||P r_k||, ttol = max(rtol ||P b||, atol) (||P b|| = dp_0 from a zero guess);
a column stops with CONVERGED_RTOL (CONVERGED_ATOL below atol) at the first k with dp_k <= ttol,
after k iterations; with DIVERGED_INDEFINITE_MAT when p.Ap = 0 or changes sign,
DIVERGED_INDEFINITE_PC when r.z changes sign, DIVERGED_NANORINF on a NaN or inf product, and
DIVERGED_MAX_IT (KSP_DIVERGED_ITS) after ``max_it`` iterations. A stopped column is frozen: its step lengths are 0, so
its iterate and residual stay exactly what they were when it stopped, while the other columns go on.

The CGs of fempdl, and why there are four:

* PETSc's KSPCG: a layer's solve on the PETSc path (``KSPOptions.preset("cg")``), one sample at a time;
* :func:`capped_cg` and :func:`converged_cg` here: the same recurrences and stopping rules for a batch of
  columns at once (the batched engine, :mod:`fempdl.iterative.batched`), without autograd;
* :mod:`fempdl.iterative.unrolled`'s ``"cg"`` (autograd through K steps) and
  :mod:`fempdl.iterative.reverse_cg` (the same K steps with a hand-written reverse pass, less
  memory): the differentiable K-step map of ``diff="unrolled"``;
* :func:`matrix_free_cg` here: CG on systems given only as a function of (B, n) rows, the SIP and
  Gauss-Newton normal equations J^T J dx = J^T r whose products are autograd's
  (:mod:`fempdl.methods.sip`); no preconditioner, no matrix to hand.
"""
from __future__ import annotations

import numpy as np
import torch

from fempdl.iterative.columns import column_dots, spmm_into

__all__ = ["fast_cg", "capped_cg", "converged_cg", "matrix_free_cg", "Tolerance", "UNDERFLOW"]

#: The smallest normal double. A column whose r.z falls below it stops as converged (CONVERGED_ATOL):
#: its products have left the normal range, where a step length is a ratio of numbers with few
#: significant bits left (:func:`capped_cg`).
UNDERFLOW = float(np.finfo(np.float64).tiny)


def fast_cg(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int) -> torch.Tensor:
    """At most K steps of preconditioned CG from X = 0 for R (n, B); returns X (n, B) (see :func:`capped_cg`)."""
    return capped_cg(A, P, R, K)[0]


def capped_cg(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor,
              K: int) -> tuple[torch.Tensor, np.ndarray, list, np.ndarray]:
    """K steps of preconditioned CG from X = 0 for R (n, B), each column stopping early only where
    PETSc's KSPCG under a pure cap (NORM_NONE, KSPConvergedSkip) stops.

    KSPCG's tests are on exact values: at the top of iteration k (which it counts), r.z == 0
    (CONVERGED_ATOL: a residual that is zero, or has underflowed, as CG's recursive residual does a
    few hundred iterations past convergence; here from the first r.z below :data:`UNDERFLOW`, see
    the module docstring) or r.z changing sign (DIVERGED_INDEFINITE_PC);
    after the product, p.Ap == 0 or changing sign (DIVERGED_INDEFINITE_MAT); a NaN or inf product
    (DIVERGED_NANORINF). A stopped column is frozen (step lengths 0): its iterate stays exactly what
    it was. The loop ends when no column runs. One sparse product and two column-dot passes per
    iteration; the tests cost one check per product while every column runs and every product is
    positive (an SPD matrix and preconditioner).

    Returns X (n, B) and per column the iterations (B,), the reason names (B strings; CONVERGED_ITS
    for a column that ran all K, as PETSc reports a pure cap) and the last ||P r|| (B,)."""
    X = torch.zeros_like(R)
    r = R.clone()
    buf = torch.empty_like(R)
    z = r if P is None else P * r
    p = torch.empty_like(R)
    w = torch.empty_like(R)
    stops = _CapStops(R.shape[1], K)
    beta = column_dots(r, z, buf).numpy().copy()
    stops.nonfinite(beta, 0)
    beta_old = dpi_old = None
    positive = {"beta": False, "dpi": False}       # the previous iteration's products were all > 0
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        for i in range(K):
            # KSPCG's tests at the top of iteration i + 1.
            if not stops.clean(beta, positive, "beta", first=i == 0):
                stops.stop(np.abs(beta) < UNDERFLOW, _ATOL, i + 1)
                if i:
                    stops.stop(beta * beta_old < 0, _INDEFINITE_PC, i + 1)
                if not stops.running.any():
                    break
            if i:
                b = beta / beta_old
                b[~stops.running] = 0.0
                torch.addcmul(z, p, torch.from_numpy(b), out=p)
            else:
                p.copy_(z)
            spmm_into(A, p, w)
            dpi = column_dots(p, w, buf).numpy().copy()
            if not stops.clean(dpi, positive, "dpi", first=i == 0):
                stops.nonfinite(dpi, i + 1)
                stops.stop(dpi == 0, _INDEFINITE_MAT, i + 1)
                if i:
                    stops.stop(np.sign(dpi) * np.sign(dpi_old) < 0, _INDEFINITE_MAT, i + 1)
            a = beta / dpi
            a[~stops.running] = 0.0                   # stopped columns stay exactly where they are
            a_t = torch.from_numpy(a)
            X.addcmul_(p, a_t)
            r.addcmul_(w, a_t, value=-1.0)
            if i + 1 == K or not stops.running.any():
                break                                  # KSPConvergedSkip: CONVERGED_ITS after K
            if P is not None:
                torch.mul(P, r, out=z)
            beta_old, beta, dpi_old = beta, column_dots(r, z, buf).numpy().copy(), dpi
            stops.nonfinite(beta, i + 1)
    if P is not None:
        torch.mul(P, r, out=z)
    return X, stops.its, [_REASONS[k] for k in stops.reason], column_dots(z, z, buf).sqrt().numpy()


class _CapStops:
    """Which columns of :func:`capped_cg` still run, and when and why the others stopped."""

    def __init__(self, batch: int, K: int):
        self.running = np.ones(batch, dtype=bool)
        self.all_running = True
        self.its = np.full(batch, K, dtype=np.int64)
        self.reason = np.full(batch, _ITS)

    def clean(self, values: np.ndarray, positive: dict, key: str, first: bool) -> bool:
        """True when no test can fire on ``values`` (r.z or p.Ap of every column): all columns run,
        and these values and the previous ones (unless ``first``) are finite and positive."""
        now = bool(values.min() >= UNDERFLOW) and bool(np.isfinite(values.max()))
        clean = self.all_running and now and (first or positive[key])
        positive[key] = now
        return clean

    def stop(self, where: np.ndarray, code: int, its: int) -> None:
        """Stop the running columns in ``where`` after ``its`` iterations with reason ``code``."""
        hit = self.running & where
        if hit.any():
            self.reason[hit], self.its[hit] = code, its
            self.running &= ~hit
            self.all_running = False

    def nonfinite(self, values: np.ndarray, its: int) -> None:
        if not np.isfinite(values).all():
            self.stop(~np.isfinite(values), _NANORINF, its)


class Tolerance:
    """When a column of :func:`converged_cg` stops: ``rtol``, ``atol`` and ``max_it`` as PETSc reads them
    (:meth:`fempdl.solve.options.KSPOptions.petsc_tolerances`)."""

    def __init__(self, rtol: float, atol: float, max_it: int):
        self.rtol, self.atol, self.max_it = float(rtol), float(atol), int(max_it)


# Reason names of KSPConvergedReason (the caller maps them to PETSc's codes).
_REASONS = ("CONVERGED_RTOL", "CONVERGED_ATOL", "DIVERGED_MAX_IT", "DIVERGED_INDEFINITE_MAT",
            "DIVERGED_INDEFINITE_PC", "DIVERGED_NANORINF", "CONVERGED_ITS")
_RTOL, _ATOL, _MAX_IT, _INDEFINITE_MAT, _INDEFINITE_PC, _NANORINF, _ITS = range(len(_REASONS))
_RUNNING = -1


def converged_cg(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, tol: Tolerance,
                 reference: np.ndarray | None = None) -> tuple[torch.Tensor, np.ndarray, list, np.ndarray]:
    """Preconditioned CG from X = 0 for R (n, B), each column until it meets ``tol`` (module docstring).

    ``reference`` (B,): the norms ||P b|| that rtol is relative to, when R is the residual of a
    warm start rather than b itself (``None``: dp_0, as from a zero guess).
    Returns X (n, B), the iterations (B,) int, the reason names (B strings) and the last dp (B,)."""
    n, batch = R.shape
    X = torch.zeros_like(R)
    r = R.clone()
    z = r if P is None else P * r
    buf = torch.empty_like(R)

    def products():
        """r.z and z.z per column (B,) each, as numpy."""
        rz = column_dots(r, z, buf).numpy().copy()
        return rz, (rz.copy() if P is None else column_dots(z, z, buf).numpy().copy())

    beta, zz = products()
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        dp = np.sqrt(np.abs(zz))
        ttol = np.maximum(tol.rtol * (dp if reference is None else np.asarray(reference, dtype=float)), tol.atol)
        its = np.zeros(batch, dtype=np.int64)
        reason = np.full(batch, _RUNNING)
        running = np.ones(batch, dtype=bool)
        _stop(reason, running, ~np.isfinite(dp) | ~np.isfinite(beta), dp, ttol, tol.atol)
        p = z.clone()
        w = torch.empty_like(R)
        dpi_old = np.ones(batch)
        for i in range(tol.max_it):
            if not running.any():
                break
            its[running] = i + 1
            spmm_into(A, p, w)
            dpi = column_dots(p, w, buf).numpy().copy()
            # KSPCG compares signs, not the product (which underflows to 0 past convergence).
            indefinite = (dpi == 0) | ((np.sign(dpi) * np.sign(dpi_old) < 0) if i else False)
            _stop(reason, running, ~np.isfinite(dpi), code=_NANORINF, other=indefinite, other_code=_INDEFINITE_MAT)
            a = beta / dpi
            a[~running] = 0.0                      # stopped columns stay exactly where they are
            a_t = torch.from_numpy(a)
            r.addcmul_(w, a_t, value=-1.0)
            if P is not None:
                torch.mul(P, r, out=z)
            beta_new, zz = products()
            X.addcmul_(p, a_t)
            np.copyto(dp, np.sqrt(np.abs(zz)), where=running)
            _stop(reason, running, ~np.isfinite(dp) | ~np.isfinite(beta_new), dp, ttol, tol.atol)
            if i + 1 < tol.max_it:
                # KSPCG tests these at the top of the next iteration, which it counts.
                ends = running & (beta_new * beta <= 0)
                if ends.any():
                    its[ends] = i + 2
                    _stop(reason, running, beta_new == 0, code=_ATOL, other=beta_new * beta < 0,
                          other_code=_INDEFINITE_PC)
            b = beta_new / beta
            b[~running] = 0.0
            torch.addcmul(z, p, torch.from_numpy(b), out=p)
            beta, dpi_old = beta_new, dpi
        reason[running] = _MAX_IT
    return X, its, [_REASONS[k] for k in reason], dp


def _stop(reason: np.ndarray, running: np.ndarray, nan: np.ndarray, dp=None, ttol=None, atol=0.0, *,
          code: int = _NANORINF, other=None, other_code: int = _RUNNING) -> None:
    """Stop running columns in place (``running`` cleared, ``reason`` set): those in ``nan`` with ``code``,
    then those in ``other`` with ``other_code``, then (given ``dp``) KSPConvergedDefault's test
    dp <= ttol, CONVERGED_ATOL below atol and CONVERGED_RTOL otherwise."""
    for where, value in ((nan, code), (other, other_code)):
        if where is not None and (hit := running & where).any():
            reason[hit] = value
            running &= ~hit
    if dp is not None and (done := running & (dp <= ttol)).any():
        reason[done] = np.where(dp[done] < atol, _ATOL, _RTOL)
        running &= ~done


def matrix_free_cg(normal, rhs: torch.Tensor, max_it: int, rtol: float = 0.0) -> tuple[torch.Tensor, int]:
    """CG on independent symmetric positive systems N_b dx_b = rhs_b, one per row of ``rhs`` (B, n).

    ``normal`` maps (B, n) -> (B, n) row by row; a row stops once its residual is
    below ``rtol`` times its right-hand side. Returns dx (B, n) and the number of
    iterations run (calls of ``normal``), at most ``max_it``."""
    dx = torch.zeros_like(rhs)
    r, p = rhs.clone(), rhs.clone()
    rr = (r * r).sum(-1)
    stop = (rtol * rhs.norm(dim=-1)) ** 2
    iterations = 0
    for _ in range(max_it):
        active = rr > stop
        if not bool(active.any()) or not bool((rr > 0).any()):
            break
        q = normal(p)
        pq = (p * q).sum(-1)
        alpha = torch.where(active & (pq > 0), rr / torch.where(pq > 0, pq, 1.0), 0.0)
        dx += alpha[:, None] * p
        r -= alpha[:, None] * q
        rr_new = (r * r).sum(-1)
        beta = torch.where(rr > 0, rr_new / torch.where(rr > 0, rr, 1.0), 0.0)
        p = r + beta[:, None] * p
        rr = rr_new
        iterations += 1
    return dx, iterations
