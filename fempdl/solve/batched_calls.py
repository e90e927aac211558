"""The batched engine's side of a :class:`~fempdl.solve.linear_system.LinearSystem`: whether a call runs
on it, the engine's copy of the current matrix, and solves of rows of any scale.

The engine (:class:`fempdl.iterative.batched.BatchedEngine`) solves all B right-hand sides of a call at
once, rows of R (B, n); this keeps its copy of A current by the system's matrix version and scales rows far
from 1 by powers of two around it (:mod:`fempdl.solve.scaling`).
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

from fempdl.solve.options import KSPOptions
from fempdl.solve.scaling import row_exponents

__all__ = ["BatchedCalls"]


class BatchedCalls:
    """A system's calls on ``engine``, for solver options whose engine is not ``"petsc"``."""

    def __init__(self, engine):
        self.engine = engine
        self._version = -1          # the matrix version the engine's copy holds

    def runs(self, options: KSPOptions, batch: int, per_sample_matrix: bool, comm_size: int,
             A: PETSc.Mat | None = None) -> bool:
        """Whether a call of ``batch`` samples on ``A`` runs on the engine (see ``KSPOptions.engine``)."""
        if per_sample_matrix or self.engine.unsupported_reason(options, comm_size) is not None:
            return False  # e.g. the cap was lifted to max_it=None after construction
        if options.engine == "batched":
            return True
        # Measured rules (benchmarks/bench_batched_auto.py), for both directions' solvers.
        nnz = None if A is None else self.engine.nonzeros(A)
        return all(self.engine.faster_than_petsc(batch, opts.ksp_type, options=opts, nnz=nnz)
                   for opts in (options, options.adjoint_options))

    def solve(self, A: PETSc.Mat, version: int, R: np.ndarray, options: KSPOptions, *, transpose: bool,
              X0: np.ndarray | None = None):
        """(X, seconds, outcome) of A X = R (A^T with ``transpose``) for R's rows, from X0's rows if given.
        Rows far from 1 are solved scaled by a power of two (exact); a user's atol is on the data as given,
        so with one the rows are solved as they are."""
        if self._version != version:
            self.engine.load(A)
            self._version = version
        e = np.zeros((0, 1), dtype=int) if options.atol else row_exponents(R, X0)[:, None]
        if e.any():
            R = np.ldexp(R, -e)
            X0 = None if X0 is None else np.ldexp(X0, -e)
        X, seconds, outcome = self.engine.solve(R, options, transpose=transpose, X0=X0)
        return (np.ldexp(X, e) if e.any() else X), seconds, outcome

    def matmul(self, X: np.ndarray, transpose: bool = False) -> np.ndarray:
        """A X^T's rows (A^T with ``transpose``) on the engine's copy of A."""
        return self.engine.matmul(X, transpose=transpose)
