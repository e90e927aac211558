"""PRDP's gap: how far the capped metric lies from the reference one, and the cap that closes it.

A model trained through capped solves is judged with converged ones. The gap
is the relative difference of the same validation computed both ways,
|capped - reference| / min(capped, reference). An open gap (above the
tolerance) means the cap still changes how the model is judged: the capped
solve is far from converged at this model, or the network leans on the cap's
bias. Either way training at that cap teaches the wrong physics, and the
remedy is a larger cap at once, not one plateau at a time.

:func:`closing_cap` finds it with the validation itself: K doubles from the
current cap (never above the bound) until the capped metric lies within the
tolerance, then the last open and the first closed cap are bisected to within
an eighth of the smaller. Each probe is one capped validation; a search from
K to K' costs about 2 log2(K' / K) + 3 of them, once per opening.
:func:`grown_cap` is the step taken where only numbers are known (a metric and
its capped value passed to ``PRDP.step``): K doubles.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

__all__ = ["GapSearch", "closing_cap", "grown_cap", "open_gap_message", "relative_gap"]


def relative_gap(capped: float, reference: float) -> float:
    """|capped - reference| / min(capped, reference), both > 0."""
    return abs(capped - reference) / min(capped, reference)


@dataclasses.dataclass(frozen=True)
class GapSearch:
    """The result of :func:`closing_cap`: the cap found, whether the gap is closed there (False: the
    bound was reached with it open), and every probe as (K, capped metric)."""

    k: int
    closed: bool
    probes: tuple[tuple[int, float], ...]


def grown_cap(k: int, least: int, bound: int | None) -> int:
    """The next cap while the gap is open and only numbers are known: max(K + least, 2 K), at most ``bound``."""
    k = max(k + least, 2 * k)
    return k if bound is None else min(k, bound)


def closing_cap(capped_at: Callable[[int], float], reference: float, k: int, bound: int, tolerance: float,
                least: int = 1) -> GapSearch:
    """The smallest cap above ``k`` (to within an eighth) whose capped metric lies within ``tolerance`` of
    ``reference``, found by doubling up to ``bound`` and bisection (module docstring).

    Args:
        capped_at: runs the validation with the caps at K and returns its metric.
        reference: the validation metric at reference physics.
        k: the current cap, where the gap is open.
        bound: the largest cap to probe (``k_cap``).
        tolerance: the gap at which a cap counts as closed.
        least: the least step of the doubling (PRDP's ``dk``).
    """
    probes: list[tuple[int, float]] = []

    def closed(cap: int) -> bool:
        value = capped_at(cap)
        probes.append((cap, value))
        return relative_gap(value, reference) <= tolerance

    low, high = k, None                    # low: open; high: closed
    while low < bound:
        probe = min(max(low + least, 2 * low), bound)
        if closed(probe):
            high = probe
            break
        low = probe
    if high is None:
        return GapSearch(k=bound, closed=False, probes=tuple(probes))
    while high - low > max(1, low // 8):
        middle = (low + high) // 2
        if closed(middle):
            high = middle
        else:
            low = middle
    return GapSearch(k=high, closed=True, probes=tuple(probes))


def open_gap_message(k: int, capped: float, reference: float, tolerance: float, k_cap: int | None) -> str:
    """What PRDP says when training ends with the gap open at cap ``k``."""
    return (f"PRDP ends with the gap open: at K = {k} the validation metric is {capped:.4g} with the capped solves "
            f"and {reference:.4g} with converged ones ({100 * relative_gap(capped, reference):.0f}% apart, more "
            f"than gap = {tolerance:g}): the model leans on the cap, or the cap is far from converged at this "
            f"model. Train on at a larger cap (k_cap = {k_cap}), or judge the model only with converged physics")
