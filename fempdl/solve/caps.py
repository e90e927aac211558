"""The iteration caps of a solve, as one value.

A linear solve has one cap, K iterations (``max_it``). A Newton solve has two: N Newton steps
(``max_it``) and K iterations of each step's inner Krylov solve (``inner_max_it``). ``None``
means "converged": the solve runs to its tolerances. A system, a layer and a PRDP target read
and write their caps as a :class:`Caps`, so a cap is saved, compared, sent between ranks and
put back as one thing whatever kind of solve it belongs to.

Example:
    >>> layer.caps = Caps(4, inner_max_it=20)     # a NonlinearSolveLayer: 4 Newton steps of 20
    >>> layer.caps.max_it
    4
"""
from __future__ import annotations

import dataclasses

from fempdl.core.checks import check_int

__all__ = ["Caps"]


@dataclasses.dataclass(frozen=True)
class Caps:
    """A solve's caps: ``max_it`` (a linear solve's K, a Newton solve's N) and ``inner_max_it`` (a Newton
    step's inner K; ``None`` on a linear solve). Each is an int >= 1 or ``None`` (converged)."""

    max_it: int | None = None
    inner_max_it: int | None = None

    def __post_init__(self):
        for name in ("max_it", "inner_max_it"):
            value = getattr(self, name)
            if value is not None:
                check_int(f"Caps.{name}", value, minimum=1)
                object.__setattr__(self, name, int(value))      # numpy ints compare and pickle as ints

    def __repr__(self) -> str:          # a linear solve's reads Caps(max_it=5), without its empty inner cap
        inner = "" if self.inner_max_it is None else f", inner_max_it={self.inner_max_it}"
        return f"Caps(max_it={self.max_it}{inner})"
