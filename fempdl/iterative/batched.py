"""Capped Richardson, CG and GMRES for a whole batch: one sparse-times-dense product per iteration.

For B right-hand sides stacked as the columns of R (n, B), K iterations of

    X_0 = 0,   X_{k+1} = X_k + omega D^{-1} (R - A X_k)

(and the same with A^T for the transposed solve) are exactly what PETSc's
KSPRICHARDSON + PCJACOBI computes column by column, with the same operations
in the same order per entry; only the summation order inside a sparse row
product may differ, so the iterates agree to round-off (about 1e-15
relative). CG and GMRES(m) run :func:`fempdl.iterative.unrolled.solve`'s KSPCG and
KSPGMRES recurrences the same way. PCJACOBI replaces a zero diagonal entry by 1, and so does this engine.

The operator is a torch CSR copy of the assembled PETSc matrix (serial only),
refreshed when the matrix is reassembled. Reading the matrix once per
iteration for all B columns, and torch's threaded sparse kernels, make this
1.9x (4k DOFs) to 2x (66k DOFs, 2 threads) faster per right-hand side than B
separate KSP solves at K = 200, B = 32 (``scripts/bench_layer.py``).

This module knows PETSc and torch, nothing of UFL.
"""
from __future__ import annotations

import time

import numpy as np
import torch
from petsc4py import PETSc

from fempdl.iterative import unrolled
from fempdl.ksp_adjoint import KSPOptions, petsc_to_scipy
from fempdl.iterative.sparse import sparse_to_torch

__all__ = ["BatchedEngine"]

_OWN_OPTIONS = frozenset({"ksp_richardson_scale"})


class BatchedEngine:
    """Batched capped Richardson, CG and GMRES (+ Jacobi) on a torch copy of a PETSc matrix."""

    def __init__(self):
        self._A = self._At = self._dinv = None

    @staticmethod
    def unsupported_reason(options: KSPOptions, comm_size: int) -> str | None:
        """Why this engine cannot run ``options`` (``None`` if it can)."""
        if comm_size > 1:
            return "it runs on one process (the mesh is distributed over several)"
        for opts in (options, options.adjoint_options):
            if opts.ksp_type not in ("richardson", "cg", "gmres") or opts.pc_type not in ("jacobi", "none"):
                return (f"it implements Richardson, CG and GMRES with Jacobi or no preconditioner, not "
                        f"{opts.ksp_type}+{opts.pc_type}")
            if not opts.capped or any(v is not None for v in (opts.rtol, opts.atol, opts.divtol)):
                return "it runs a pure iteration cap (max_it set; rtol, atol and divtol unset)"
            extra = set(opts.petsc_options) - _OWN_OPTIONS
            if extra:
                return f"it does not interpret petsc_options {sorted(extra)}"
            if opts.options_prefix is not None:
                return f"it reads no PETSc options (options_prefix={opts.options_prefix!r} is set)"
        return None

    @staticmethod
    def faster_than_petsc(batch: int, n: int) -> bool:
        """Measured rule (scripts/bench_layer.py): batching pays from B = 2 when
        torch has two or more threads, or on one thread while the (n, B) iterate
        stays cache-sized."""
        return batch >= 2 and (torch.get_num_threads() >= 2 or batch * n <= 2 ** 20)

    def load(self, A: PETSc.Mat) -> None:
        """Copy the current entries of ``A`` (call again after it is reassembled)."""
        S = petsc_to_scipy(A)
        d = S.diagonal()
        self._A = sparse_to_torch(S)
        self._At = sparse_to_torch(S.T.tocsr())
        safe = np.where(d != 0.0, d, 1.0)  # PCJACOBI's treatment of a zero diagonal
        self._dinv = torch.from_numpy(1.0 / safe)[:, None]

    def solve(self, R: np.ndarray, options: KSPOptions, *, transpose: bool = False,
              X0: np.ndarray | None = None) -> tuple[np.ndarray, float]:
        """``options.max_it`` iterations for the rows of R (B, n), from zero or from
        the rows of ``X0`` (B, n); returns (X (B, n), seconds)."""
        if self._A is None:
            raise RuntimeError("BatchedEngine.load(A) must be called before solve")
        t0 = time.perf_counter()
        op = self._At if transpose else self._A
        rhs = torch.from_numpy(np.ascontiguousarray(R.T))
        start = None if X0 is None else torch.from_numpy(np.array(X0.T))
        scale = float(options.petsc_options.get("ksp_richardson_scale", 1.0))
        precondition = options.pc_type == "jacobi"
        with torch.no_grad():
            if options.ksp_type in ("cg", "gmres"):
                X = unrolled.solve(options.ksp_type, op, self._dinv if precondition else None, rhs,
                                   options.max_it, restart=options.gmres_restart or 30, X0=start)
            else:
                # In place: nothing is differentiated here, so no iterate needs keeping.
                step = (self._dinv if precondition else torch.ones_like(self._dinv)) * scale
                X = torch.zeros_like(rhs) if start is None else start
                for _ in range(options.max_it):
                    X.addcmul_(step, rhs - op @ X)
        return np.ascontiguousarray(X.T.numpy()), time.perf_counter() - t0

    def matmul(self, X: np.ndarray, *, transpose: bool = False) -> np.ndarray:
        """A X^T (or A^T X^T) for the rows of X (B, n), as rows (B, n)."""
        op = self._At if transpose else self._A
        return np.ascontiguousarray((op @ torch.from_numpy(np.ascontiguousarray(X.T))).T.numpy())
