"""Solver health: whether a capped solve is coarse or garbage.

PRDP trains on capped solves because a coarse solve still points the right way.
A capped solve whose residual grew, or stayed where it started, does not: the
network would train on garbage until the validation metric noticed. A solve
handed a :class:`CallHealth` (``system.solve(..., health=CallHealth(limit))``,
which a layer's :class:`HealthCheck` does) measures into it, for every capped
forward solve of the call, the residual ratio

    rho = ||r_K|| / ||r_0||,   r = b - A x (linear), r = F(u) (Newton),

from the start x_0 (zero, or the warm start) to the K-th iterate, in the
2-norm over every rank's owned DOFs, and keeps the largest over the call's
samples (:attr:`CallHealth.ratio`). A solve that met a tolerance, or whose
final residual lies within the round-off of the terms it sums
(:func:`~fempdl.solve.round_off.round_off_floor`: a warm start at the
solution), counts as healthy. The measure costs one matrix-vector product per
capped sample (two from a warm start); a Newton solve has its residuals already.

:class:`HealthCheck` is what a layer does with it (:class:`~fempdl.layer.system_layer.SystemLayer`):
a training call whose ratio exceeds ``limit`` asks ``refine`` for a larger cap
and solves again, before anything downstream sees the garbage.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from fempdl.core.checks import is_real, python_number
from fempdl.solve.round_off import round_off_floor

__all__ = ["HealthCheck", "CallHealth"]


@dataclasses.dataclass(frozen=True)
class HealthCheck:
    """A layer's rule for garbage solves.

    Attributes:
        limit: a capped training solve with rho > ``limit`` is garbage (1: its residual did not shrink).
        refine: called with rho; raises the caps of every layer it moves and returns True, or returns
            False when they cannot rise (then the layer warns and keeps the solve).
        adjoint_limit: the limit of an adjoint solve whose gradient is the implicit-function approximation
            (its error is about the adjoint's: a solve that merely shrank is not enough); ``None``: ``limit``.
    """

    limit: float
    refine: Callable[[float], bool]
    adjoint_limit: float | None = None

    def __post_init__(self):
        for limit in (self.limit, 1.0 if self.adjoint_limit is None else self.adjoint_limit):
            if not is_real(limit) or not 0.0 < limit < math.inf:
                raise ValueError(f"a health limit must be a finite number > 0 (a residual ratio), got {limit!r}")
        object.__setattr__(self, "limit", python_number(self.limit))
        object.__setattr__(self, "adjoint_limit", python_number(self.adjoint_limit))
        if not callable(self.refine):
            raise TypeError(f"refine must be callable, got {type(self.refine).__name__}")

    def limit_for(self, direction: str, exact: bool) -> float:
        """The limit of a ``direction`` ("forward" or "adjoint") solve of a layer whose capped gradient is
        (``exact``) or is not the derivative of the capped map."""
        if direction == "forward" or exact or self.adjoint_limit is None:
            return self.limit
        return self.adjoint_limit


class CallHealth:
    """The largest residual ratio rho of one call's capped forward solves (``ratio``; ``None``: none was
    measured), for a health limit ``limit``. The caller makes one per call and hands it to the solve, which
    adds each capped sample's residual norms."""

    def __init__(self, limit: float):
        self.limit, self.ratio = limit, None

    def add(self, final: float, start: float, floor: Callable[[], float]) -> None:
        """One sample's residual norms; ``floor()``, the round-off level under which a final residual is a
        solution's, is computed only for a ratio above the limit (it costs about a matrix-vector product)."""
        rho = final / start if start > 0.0 else (0.0 if final == 0.0 else math.inf)
        if not math.isfinite(final):
            rho = math.inf
        elif rho > self.limit and final <= floor():
            rho = 0.0
        self.ratio = rho if self.ratio is None else max(self.ratio, rho)

    def add_rows(self, finals, starts, x_norms, b_norms, a_norm: Callable[[], float]) -> None:
        """Many samples' residual norms at once (sequences of floats); ``a_norm()``, ||A||_inf, is computed
        at most once, for the first ratio above the limit."""
        norm: list = []

        def floor(x: float, b: float) -> float:
            if not norm:
                norm.append(a_norm())
            return round_off_floor(norm[0], x, b)

        for final, start, x, b in zip(finals, starts, x_norms, b_norms):
            self.add(float(final), float(start), lambda x=x, b=b: floor(float(x), float(b)))

