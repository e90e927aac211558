"""Solves of right-hand sides of any representable magnitude, by exact power-of-two scaling.

A linear solve is homogeneous: x(s b, s x0) = s x(b, x0) for a direct solve and for every
Krylov or stationary iteration, capped or not (each step is a linear combination with
coefficients that are ratios of inner products of the iterates). Where the data lie far
from 1, the iteration's inner products underflow to zero (||b|| below about 1e-154 squares
to a subnormal, a subnormal b to 0: the solve "converges" at iteration 0 to x = 0) or
overflow to inf (above about 1e154: CG reports an indefinite operator). A solve whose data
lie outside ``[2^-SAFE_EXPONENT, 2^SAFE_EXPONENT]`` therefore runs on 2^-e b (and 2^-e x0),
with e the binary exponent of max |b| (and max |x0|), and returns 2^e x. Multiplying by a
power of two is exact away from the subnormal range, so the solve's iterates are those of
the unscaled solve in exact arithmetic; data within the range are left untouched, bit for bit.
"""
from __future__ import annotations

import math

import numpy as np
from petsc4py import PETSc

__all__ = ["SAFE_EXPONENT", "scale_exponent", "scale_vec", "row_exponents"]

#: Data whose largest entry lies within 2^-SAFE_EXPONENT .. 2^SAFE_EXPONENT (1e-60 .. 1.6e60) are solved
#: as they are: their squares, summed over any mesh, stay far inside float64's normal range.
SAFE_EXPONENT = 200
# The largest power of two applied in one multiplication (2^1023 is float64's largest).
_STEP = 1000


def scale_exponent(*max_abs: float) -> int:
    """The binary exponent e to divide data by (0 when the largest of ``max_abs`` is in the safe range,
    zero, or not finite: non-finite data fail the solve as they are)."""
    m = max(max_abs)
    if not math.isfinite(m) or m == 0.0:
        return 0
    e = math.frexp(m)[1]
    return e if abs(e) > SAFE_EXPONENT else 0


def scale_vec(vec: PETSc.Vec, e: int) -> None:
    """vec *= 2^e, in steps that stay representable (a subnormal needs 2^1046)."""
    while e:
        step = max(-_STEP, min(_STEP, e))
        vec.scale(2.0 ** step)
        e -= step


def row_exponents(*blocks: np.ndarray | None) -> np.ndarray:
    """The exponent of :func:`scale_exponent` for each row of the (B, n) blocks together (``None`` skipped)."""
    blocks = [np.abs(np.asarray(b, dtype=float)) for b in blocks if b is not None]
    m = np.max([b.max(axis=1) if b.shape[1] else np.zeros(b.shape[0]) for b in blocks], axis=0)
    return np.array([scale_exponent(v) for v in m], dtype=int)
