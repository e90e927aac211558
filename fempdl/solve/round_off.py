"""The round-off floor: the residual an exact solution leaves in float64.

Each entry of r = b - A x (linear) or F(u) = J u - f (Newton, linearised)
sums products whose rounding is about eps |A| |x| + eps |b|, so the residual
of the exact discrete solution, computed in floating point, is not zero but

    floor = FLOOR_RESIDUAL eps (||A||_inf ||x||_2 + ||b||_2).

A residual at or below it is a solution's: the health check counts such a solve
as healthy (:mod:`fempdl.solve.health`), and a Newton solve that stalls there ends
as converged (:mod:`fempdl.solve.newton_stop`).
"""
from __future__ import annotations

import numpy as np
from petsc4py import PETSc

__all__ = ["FLOOR_RESIDUAL", "round_off_floor"]

#: The residual's round-off, in units of eps (||A||_inf ||x||_2 + ||b||_2): room for the sum over
#: entries and cancellation, and still orders of magnitude below a singular J's stuck residual.
FLOOR_RESIDUAL = 1e4
_EPS = float(np.finfo(np.float64).eps)


def round_off_floor(A: PETSc.Mat | float, x_norm: float, b_norm: float = 0.0) -> float:
    """FLOOR_RESIDUAL eps (||A||_inf ||x|| + ||b||) (``A``: the matrix, or its infinity norm)."""
    a_norm = A if isinstance(A, float) else A.norm(PETSc.NormType.INFINITY)
    return FLOOR_RESIDUAL * _EPS * (a_norm * x_norm + b_norm)
