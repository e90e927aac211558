"""Binomial checkpointing (Griewank and Walther's revolve) as a lazy ``checkpoint_schedules`` schedule.

N steps are reversed with s snapshots, states kept in memory (u_0's among them).
With beta(k, r) = binom(k + r, k), the most steps k snapshots reverse when no
step runs forward more than r times besides the run that stores its adjoint
dependencies, the rule from a kept state u_l, with m steps l ... l + m - 1 left
to reverse and k snapshots for them (u_l's included), is:

- m = 1: run step l keeping (u_l, u_{l+1}), reverse it; u_l's snapshot is freed;
- k = 1: advance to u_{l+m-1}, run and reverse step l + m - 1, restore u_l and
  go on with m - 1 steps;
- otherwise split at l + j: advance j steps, keep u_{l+j} in a snapshot,
  reverse the m - j steps after it with k - 1 snapshots, then restore u_l and
  reverse the first j steps with k snapshots. With r the repetition number of
  (m, k), beta(k, r - 1) < m <= beta(k, r), j is the largest value in

      max(beta(k, r-2), m - beta(k-1, r)) <= j <= min(beta(k, r-1), m - beta(k-1, r-1)).

Over that range the cost j + T(j, k) + T(m - j, k - 1) does not change with j
(T(., k) grows by r - 1 a step up to beta(k, r - 1), T(., k - 1) by r up to
beta(k - 1, r)), and it equals the fewest forward steps any schedule with k
snapshots achieves (Griewank and Walther, ACM TOMS 26, 2000),

    T(m, k) = r m - beta(k + 1, r - 1),

besides the m runs that keep a step's adjoint dependencies. Over a rollout
(m = N, k = s) the first sweep is N of the T(N, s) + N runs, so T(N, s) steps
run again, as under ``checkpoint_schedules.Revolve(N, s)``.

The recursion is kept as a stack of snapshot positions (the part after the
split always runs first, the part before it is a tail call), so the schedule
holds O(s) integers and makes each action, as the consumer asks for it, from
O(log r) binomials: nothing is built up front, whatever N.

With s >= N every state fits: the first sweep keeps them all and no step runs twice.
"""
from __future__ import annotations

from math import comb

import checkpoint_schedules as cs

from fempdl.core.checks import is_int

__all__ = ["BinomialRevolve", "recomputed_steps"]

_RAM, _WORK = cs.StorageType.RAM, cs.StorageType.WORK


def recomputed_steps(steps: int, snapshots: int) -> int:
    """The steps :class:`BinomialRevolve` runs again after the first sweep: T(N, s) of the module
    docstring for s < N, 0 for s >= N."""
    if snapshots >= steps:
        return 0
    r = _repetitions(steps, snapshots)
    return r * steps - comb(snapshots + r, snapshots + 1)


class BinomialRevolve(cs.CheckpointSchedule):
    """Reverse ``steps`` steps with ``snapshots`` states kept in memory (module docstring): the actions of
    ``checkpoint_schedules.Revolve(steps, snapshots)``'s kind (Forward, Copy/Move from RAM, Reverse) and
    its number of steps run again, made one by one as they are iterated."""

    def __init__(self, steps: int, snapshots: int):
        for name, value in (("steps", steps), ("snapshots", snapshots)):
            if not is_int(value) or value < 1:
                raise ValueError(f"{name} must be an int >= 1, got {value!r}")
        super().__init__(int(steps))
        self._snapshots = int(snapshots)
        self._exhausted = False

    def _iterator(self):
        steps, s = self._max_n, self._snapshots
        if s >= steps:
            yield from self._keep_all(steps)
            return
        snaps: list = []            # positions of the kept states, increasing; the top one is u_l
        end = steps                 # steps end ... N - 1 are reversed
        pos = 0                     # the working state is u_pos
        swept = False
        while True:
            while end - pos > 1:
                fresh = not snaps or snaps[-1] != pos
                if fresh:           # a split point (or u_0): its state is kept while the steps after it reverse
                    snaps.append(pos)
                k = s - len(snaps) + 1      # for steps pos ... end - 1: the free snapshots and u_pos's
                j = end - pos - 1 if k == 1 else _split(end - pos, k)
                yield cs.Forward(pos, pos + j, fresh, False, _RAM if fresh else _WORK)
                pos += j
                self._n = pos
            yield cs.Forward(pos, pos + 1, False, True, _WORK)
            self._n = pos + 1
            if not swept:
                swept = True
                yield cs.EndForward()
            yield cs.Reverse(pos + 1, pos, True)
            self._r += 1
            end = pos
            if end == 0:
                break
            pos = snaps[-1]
            if end - pos == 1:      # the snapshot's last use
                snaps.pop()
                yield cs.Move(pos, _RAM, _WORK)
            else:
                yield cs.Copy(pos, _RAM, _WORK)
            self._n = pos
        self._exhausted = True
        yield cs.EndReverse()

    def _keep_all(self, steps: int):
        yield cs.Forward(0, steps, False, True, _WORK)
        self._n = steps
        yield cs.EndForward()
        yield cs.Reverse(steps, 0, True)
        self._r = steps
        self._exhausted = True
        yield cs.EndReverse()

    @property
    def is_exhausted(self) -> bool:
        return self._exhausted

    def uses_storage_type(self, storage_type) -> bool:
        return storage_type == _RAM

    def __repr__(self) -> str:
        return f"BinomialRevolve(steps={self._max_n}, snapshots={self._snapshots})"


def _repetitions(m: int, k: int) -> int:
    """The least r with beta(k, r) >= m (m >= 2): doubling, then bisection."""
    lo, hi = 0, 1
    while comb(k + hi, k) < m:
        lo, hi = hi, 2 * hi
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if comb(k + mid, k) < m:
            lo = mid
        else:
            hi = mid
    return hi


def _split(m: int, k: int) -> int:
    """The steps to advance before the next snapshot, m >= 2 steps and k >= 2 snapshots (module docstring)."""
    r = _repetitions(m, k)
    return min(comb(k + r - 1, k), m - comb(k + r - 2, k - 1))
