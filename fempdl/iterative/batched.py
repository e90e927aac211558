"""Capped Richardson, CG and GMRES, and CG to a tolerance, for a whole batch: one sparse-times-dense
product per iteration.

For B right-hand sides stacked as the columns of R (n, B), K iterations of

    X_0 = 0,   X_{k+1} = X_k + omega D^{-1} (R - A X_k) = c + M X_k,
    M = I - omega D^{-1} A,   c = omega D^{-1} R

(and the same with A^T for the transposed solve) are what PETSc's
KSPRICHARDSON + PCJACOBI computes column by column. The engine runs the
second form: one fused sparse product per iteration that reads X and c and
writes the next iterate, the least memory traffic a Jacobi sweep can have
(``benchmarks/bench_floor.py``); the iterates agree with PETSc's to round-off. CG and GMRES(m) run
the recurrences of PETSc's KSPCG and KSPGMRES (classical Gram-Schmidt, as
:mod:`fempdl.iterative.unrolled`) in place and without autograd
(:mod:`fempdl.iterative.batched_cg`, :func:`fast_gmres`): whole-block operations, no loop over
columns. CG also runs to a tolerance (rtol or atol set, or no cap), each column stopping at its
own as KSPCG would and reporting its iterations and converged reason. PCJACOBI replaces a zero
diagonal entry by 1, and so does this engine.

The operator is a torch CSR copy of the assembled PETSc matrix (serial only,
int32 indices), refreshed when the matrix is reassembled. When batching pays
is :meth:`BatchedEngine.faster_than_petsc` (measured: ``benchmarks/bench_batched_auto.py``,
``benchmarks/bench_floor.py``, ``benchmarks/bench_krylov.py``).

This module knows PETSc and torch, nothing of UFL.
"""
from __future__ import annotations

import time

import numpy as np
import torch
from petsc4py import PETSc

from fempdl.core import tuning
from fempdl.iterative.batched_cg import Tolerance, capped_cg, converged_cg, fast_cg
from fempdl.iterative.columns import spmm_into
from fempdl.iterative.sparse import sparse_to_torch, torch_to_scipy
from fempdl.iterative.sweeps import column_groups, richardson, sweep_matrix, threads_for, torch_threads
from fempdl.solve.options import KSPOptions
from fempdl.solve.petsc import petsc_to_scipy

__all__ = ["BatchedEngine", "fast_cg", "converged_cg", "fast_gmres"]

_OWN_OPTIONS = frozenset({"ksp_richardson_scale"})

# The rule of BatchedEngine.faster_than_petsc (engine="auto"), measured on 2D P1 Poisson, 289 to 66k
# unknowns, B = 2 to 128, forward + adjoint through SolveLayer (benchmarks/bench_batched_auto.py). Per
# iteration, batched CG pays a fixed cost in torch operations per group of tuning.CG_GROUP columns
# (tens of microseconds) where PETSc's CG pays about a microsecond per solve, and saves part of
# PETSc's cost per nonzero: only a large enough matrix amortises the difference, at any batch size.
# Batched Richardson has one fused product per iteration but a fixed cost per call that a small batch
# amortises only over enough work.
#: Batched CG needs at least this many nonzeros: where batched / PETSc crosses 1 from B = 8, between
#: 7.4k nonzeros (1089 unknowns, PETSc ahead) and 29k (4225 unknowns, batched ahead).
CG_MIN_NONZEROS = 10_000
#: From this many columns batched Richardson was faster at every size and cap measured (289 unknowns
#: at K = 20 included).
AUTO_FULL_BATCH = 8
#: Below AUTO_FULL_BATCH columns, batched Richardson needs nonzeros x cap of at least this: at B = 2,
#: 0.15M and 0.38M are ties (K = 20 on 7.4k, K = 200 on 1.9k nonzeros), from 0.58M batched is ahead.
RICHARDSON_MIN_WORK = 500_000


class BatchedEngine:
    """Batched capped Richardson, CG and GMRES (+ Jacobi) on a torch copy of a PETSc matrix."""

    def __init__(self):
        self._A = self._At = self._dinv = None
        self._sweeps = {}   # (transpose, jacobi, omega) -> M = I - omega P A (or A^T), torch CSR

    @staticmethod
    def unsupported_reason(options: KSPOptions, comm_size: int) -> str | None:
        """Why this engine cannot run ``options`` (``None`` if it can)."""
        if comm_size > 1:
            return "it runs on one process (the mesh is distributed over several)"
        for opts in (options, options.adjoint_options):
            if opts.ksp_type not in ("richardson", "cg", "gmres") or opts.pc_type not in ("jacobi", "none"):
                return (f"it implements Richardson, CG and GMRES with Jacobi or no preconditioner, not "
                        f"{opts.ksp_type}+{opts.pc_type}")
            if opts.divtol is not None:
                return "it has no divergence test (divtol is set)"
            if opts.ksp_type != "cg" and not BatchedEngine.pure_cap(opts):
                return ("it runs Richardson and GMRES with a pure iteration cap (max_it set; rtol, atol and "
                        "divtol unset); only CG also runs to a tolerance")
            extra = set(opts.petsc_options) - _OWN_OPTIONS
            if extra:
                return f"it does not interpret petsc_options {sorted(extra)}"
            if opts.options_prefix is not None:
                return f"it reads no PETSc options (options_prefix={opts.options_prefix!r} is set)"
        return None

    @staticmethod
    def pure_cap(options: KSPOptions) -> bool:
        """Whether ``options`` ask for exactly ``max_it`` iterations (no tolerance)."""
        return options.capped and options.rtol is None and options.atol is None

    @staticmethod
    def faster_than_petsc(batch: int, ksp_type: str = "richardson", *, options: KSPOptions | None = None,
                          nnz: int | None = None) -> bool:
        """Whether a batch of ``batch`` solves runs faster here than as PETSc's loop of KSP solves.

        The cost of both grows with the matrix's nonzeros ``nnz`` times the iterations; what differs is
        a fixed cost per torch operation (per iteration and column group here, against PETSc's per
        solve), which only enough columns and enough nonzeros amortise. Measured rules
        (``benchmarks/bench_batched_auto.py``): Richardson from ``RICHARDSON_MIN_BATCH`` columns, and
        below :data:`AUTO_FULL_BATCH` columns only when ``nnz`` times the cap (``options.max_it``)
        reaches :data:`RICHARDSON_MIN_WORK`; CG (capped or converged) from ``CG_MIN_BATCH`` columns on
        a matrix of at least :data:`CG_MIN_NONZEROS` nonzeros; GMRES never. Without ``nnz`` only the
        batch sizes are compared (the matrix is not known yet)."""
        if ksp_type == "richardson":
            if batch < tuning.RICHARDSON_MIN_BATCH:
                return False
            if nnz is None or options is None or options.max_it is None or batch >= AUTO_FULL_BATCH:
                return True
            return nnz * options.max_it >= RICHARDSON_MIN_WORK
        if ksp_type != "cg" or batch < tuning.CG_MIN_BATCH:
            return False
        return nnz is None or nnz >= CG_MIN_NONZEROS

    @staticmethod
    def nonzeros(A: PETSc.Mat) -> int:
        """The stored entries of ``A`` (its sparsity pattern, known before the first assembly): the
        ``nnz`` of :meth:`faster_than_petsc`."""
        return int(A.getInfo()["nz_used"])

    def load(self, A: PETSc.Mat) -> None:
        """Copy the current entries of ``A`` (call again after it is reassembled)."""
        S = petsc_to_scipy(A)
        d = S.diagonal()
        self._A = sparse_to_torch(S)
        self._At = sparse_to_torch(S.T.tocsr())
        safe = np.where(d != 0.0, d, 1.0)  # PCJACOBI's treatment of a zero diagonal
        self._dinv = torch.from_numpy(1.0 / safe)[:, None]
        self._sweeps.clear()

    def _sweep_matrix(self, transpose: bool, jacobi: bool, omega: float) -> torch.Tensor:
        """M = I - omega P A (A^T when ``transpose``), P = D^{-1} or I, built once per matrix and setting."""
        key = (transpose, jacobi, omega)
        if key not in self._sweeps:
            S = torch_to_scipy(self._At if transpose else self._A)
            self._sweeps[key] = sparse_to_torch(sweep_matrix(S, omega, self._dinv[:, 0].numpy() if jacobi else None))
        return self._sweeps[key]

    def solve(self, R: np.ndarray, options: KSPOptions, *, transpose: bool = False,
              X0: np.ndarray | None = None) -> tuple[np.ndarray, float, tuple | None]:
        """Solve for the rows of R (B, n), from zero or from the rows of ``X0`` (B, n).

        A pure cap runs ``options.max_it`` iterations; CG with a tolerance (rtol or atol set, or no
        cap) runs each column until it meets it (:func:`~fempdl.iterative.batched_cg.converged_cg`).
        Returns (X (B, n), seconds, per-column outcome): the outcome is ``None`` for a pure cap, else
        (iterations (B,), reason names, final preconditioned residual norms (B,))."""
        if self._A is None:
            raise RuntimeError("BatchedEngine.load(A) must be called before solve")
        t0 = time.perf_counter()
        op = self._At if transpose else self._A
        rhs = torch.from_numpy(np.ascontiguousarray(R.T))
        start = None if X0 is None else torch.from_numpy(np.array(X0.T))
        scale = float(options.petsc_options.get("ksp_richardson_scale", 1.0))
        precondition = options.pc_type == "jacobi"
        if options.ksp_type == "richardson":
            M = self._sweep_matrix(transpose, precondition, scale)
            X = richardson(M, rhs * (self._dinv * scale if precondition else scale), options.max_it, start)
            return np.ascontiguousarray(X.T.numpy()), time.perf_counter() - t0, None
        # A warm start is the solve of the residual equation, as in PETSc. CG's small groups may
        # run on one thread; GMRES's batched Gram-Schmidt keeps them all.
        threads = (threads_for(op.values().numel(), min(tuning.CG_GROUP, rhs.shape[1]))
                   if options.ksp_type == "cg" else None)
        outcome = None
        with torch.no_grad(), torch_threads(threads):
            res = rhs if start is None else rhs - op @ start
            P = self._dinv if precondition else None
            if options.ksp_type == "gmres":
                X = fast_gmres(op, P, res, options.max_it, options.gmres_restart or 30)
            elif self.pure_cap(options):
                X, outcome = self._capped_cg(op, P, res, options.max_it)
            else:
                X, outcome = self._converged_cg(op, P, rhs, res, start is not None, options)
            if start is not None:
                X.add_(start)
        return np.ascontiguousarray(X.T.numpy()), time.perf_counter() - t0, outcome

    @staticmethod
    def _capped_cg(op, P, res, K: int) -> tuple[torch.Tensor, tuple | None]:
        """K capped CG iterations per column, group by group (:func:`~fempdl.iterative.batched_cg.capped_cg`);
        the outcome is ``None`` (a pure cap's record) unless some column stopped as KSPCG would."""
        parts = [capped_cg(op, P, res[:, i:i + w].contiguous(), K)
                 for i, w in column_groups(res.shape[1], tuning.CG_GROUP)]
        X = torch.cat([part[0] for part in parts], dim=1)
        outcome = tuple(np.concatenate([np.asarray(part[k]) for part in parts]) for k in (1, 2, 3))
        return X, (None if (outcome[1] == "CONVERGED_ITS").all() else outcome)

    @staticmethod
    def _converged_cg(op, P, rhs, res, warm: bool, options: KSPOptions) -> tuple[torch.Tensor, tuple]:
        """CG to the tolerance of ``options`` per column, group by group; rtol is relative to
        ||P b|| (KSPConvergedDefault with a nonzero guess), which from zero is the first residual's."""
        tols = options.petsc_tolerances()
        tol = Tolerance(tols["rtol"], tols["atol"], tols["max_it"])
        reference = ((rhs if P is None else P * rhs).norm(dim=0).numpy() if warm else None)
        parts = [converged_cg(op, P, res[:, i:i + w].contiguous(), tol,
                              None if reference is None else reference[i:i + w])
                 for i, w in column_groups(res.shape[1], tuning.CG_GROUP)]
        X = torch.cat([part[0] for part in parts], dim=1)
        outcome = tuple(np.concatenate([np.asarray(part[k]) for part in parts]) for k in (1, 2, 3))
        return X, outcome

    def matmul(self, X: np.ndarray, *, transpose: bool = False) -> np.ndarray:
        """A X^T (or A^T X^T) for the rows of X (B, n), as rows (B, n)."""
        op = self._At if transpose else self._A
        with torch_threads(threads_for(op.values().numel(), X.shape[0])):   # a small product: one thread
            return np.ascontiguousarray((op @ torch.from_numpy(np.ascontiguousarray(X.T))).T.numpy())


# ------------------------------------------------------------------ GMRES
# In place and without autograd: the engine's solves never need an iterate kept. It runs the
# recurrences of fempdl.iterative.unrolled.gmres (PETSc's KSPGMRES) for all columns at once.

def fast_gmres(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int, restart: int) -> torch.Tensor:
    """K iterations of left-preconditioned GMRES(restart) with classical Gram-Schmidt from X = 0,
    as :func:`fempdl.iterative.unrolled.gmres` (PETSc's KSPGMRES); R (n, B), returns X (n, B).

    The basis is kept sample-major, (B, m + 1, n), so that the Gram-Schmidt
    products for all columns are two batched matrix products. It always runs K iterations: past
    convergence PETSc's KSPGMRES may stop sooner, at a restart whose recursive residual has drifted
    from the true one (DIVERGED_BREAKDOWN, which the PETSc path accepts as an exact solve); the
    iterates agree to round-off, the counts do not."""
    n, batch = R.shape
    dtype = R.dtype
    m = min(restart, K)
    V = torch.empty(batch, m + 1, n, dtype=dtype)
    X = torch.zeros_like(R)
    v = torch.empty_like(R)           # the current basis vector, column-major for the SpMM
    w = torch.zeros_like(R)
    done = 0
    while done < K:
        steps = min(restart, K - done)
        spmm_into(A, X, w)
        r = R - w
        if P is not None:
            r.mul_(P)
        beta = r.norm(dim=0)
        broken = beta == 0
        V[:, 0].copy_((r / torch.where(broken, torch.ones_like(beta), beta)).T)
        H = torch.zeros(batch, steps + 1, steps, dtype=dtype)
        for j in range(steps):
            v.copy_(V[:, j].T)
            spmm_into(A, v, w)
            if P is not None:
                w.mul_(P)
            wt = w.T.contiguous()                                   # (B, n)
            basis = V[:, :j + 1]                                    # (B, j + 1, n)
            # Row-vector products (1 x n times n x (j + 1)): several times faster in torch's
            # CPU bmm than the column-vector form.
            h = torch.bmm(wt[:, None, :], basis.transpose(1, 2))    # (B, 1, j + 1)
            wt[:, None, :].baddbmm_(h, basis, alpha=-1.0)
            h = h[:, 0, :]
            h_next = wt.norm(dim=1)
            newly = ~broken & (h_next <= 1e-14 * beta)
            pad = broken
            broken = broken | newly
            H[:, :j + 1, j] = torch.where(pad[:, None], torch.zeros_like(h), h)
            zero, one = torch.zeros_like(h_next), torch.ones_like(h_next)
            H[:, j + 1, j] = torch.where(pad, one, torch.where(broken, zero, h_next))
            scale = torch.where(broken, zero, 1.0 / torch.where(broken, one, h_next))
            torch.mul(wt, scale[:, None], out=V[:, j + 1])
        rhs = torch.zeros(batch, steps + 1, 1, dtype=dtype)
        rhs[:, 0, 0] = beta
        Q, T = torch.linalg.qr(H)
        y = torch.linalg.solve_triangular(T, Q.transpose(1, 2) @ rhs, upper=True)   # (B, steps, 1)
        X.add_(torch.bmm(y.transpose(1, 2), V[:, :steps])[:, 0, :].T)
        done += steps
    return X
