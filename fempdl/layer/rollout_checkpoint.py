"""A Rollout's gradient under a checkpoint schedule: O(s n) states kept instead of O(N n).

The forward sweep runs the N steps without autograd; the backward sweep runs
the adjoint of each step in reverse,

    lam_N = dJ/du_N,   lam_k = dJ/du_k + (dS_k/du_k)^T lam_{k+1},   dJ/dm += (dS_k/dm_k)^T lam_{k+1},

where (dS_k/d.)^T lam is the step layer's own adjoint at the states (u_k,
u_{k+1}) (``system.adjoint``: one transposed solve per sample; through a warm
start also the adjoint residual), at the Constants and caps step k's forward
ran with. Which states are kept, and which steps are run again from a kept
state, follows a schedule in the action language of the ``checkpoint_schedules``
package (pyadjoint's and Firedrake's): ``"all"`` keeps every state (no step run
twice); ``("revolve", s)`` keeps s states in memory under binomial
checkpointing, the fewest steps run again for s snapshots, by
:class:`~fempdl.layer.revolve.BinomialRevolve`, which makes its actions as
they are asked for (``checkpoint_schedules.Revolve`` builds the whole schedule
before the first step); ``("multistage", s_ram, s_disk)`` keeps s_ram in
memory and s_disk on disk (``disk_dir``). The gradient is the same under
every schedule: a step run again from the same state with the same Constants
and caps gives the same bits. :class:`ScheduleStats` counts what ran.

A step whose adjoint reads no state (a linear step, the gradients asked for all of right-hand-side
terms: (dS_k/du_k)^T lam = C^T A^-T lam with A and C free of u) needs no schedule:
:class:`StatelessRollout` keeps only the output states and runs every adjoint once, nothing again.

This module runs a schedule's actions on NumPy arrays; the torch side is
:mod:`fempdl.layer.rollout`.
"""
from __future__ import annotations

import dataclasses
import os
import tempfile

import checkpoint_schedules as cs
import numpy as np

from fempdl.core.checks import is_int
from fempdl.layer.revolve import BinomialRevolve

__all__ = ["ScheduleStats", "make_schedule", "CheckpointedRollout", "StatelessRollout"]


@dataclasses.dataclass
class ScheduleStats:
    """What the last checkpointed rollout ran: ``steps`` forward steps of the first sweep,
    ``recomputed`` steps run again from kept states, ``reused`` steps a schedule asked to run again
    whose result the last reversal held (u_k+1, the first state of step k+1's adjoint: not run),
    ``adjoint_steps``, and the most states held at once in memory and on disk. In memory counts the
    snapshots and the working pair (u_k, u_k+1) of the step whose adjoint runs: s + 2 for
    ``("revolve", s)`` (N + 1 when s >= N), N + 1 for ``"all"``."""

    steps: int = 0
    recomputed: int = 0
    reused: int = 0
    adjoint_steps: int = 0
    most_in_memory: int = 0
    most_on_disk: int = 0


def make_schedule(spec, steps: int) -> cs.CheckpointSchedule:
    """The ``checkpoint_schedules`` schedule of ``spec`` (module docstring) for ``steps`` steps."""
    if spec == "all":
        return cs.SingleMemoryStorageSchedule()       # online: finalised at N by the forward sweep
    if isinstance(spec, tuple) and spec and spec[0] == "revolve" and len(spec) == 2:
        return BinomialRevolve(steps, _count("revolve snapshots", spec[1]))
    if isinstance(spec, tuple) and spec and spec[0] == "multistage" and len(spec) == 3:
        in_ram, on_disk = spec[1], spec[2]
        for name, value in (("in memory", in_ram), ("on disk", on_disk)):
            if not is_int(value) or value < 0:
                raise ValueError(f"multistage snapshots {name} must be an int >= 0, got {value!r}")
        if in_ram + on_disk < 1:
            raise ValueError("a multistage schedule needs at least one snapshot")
        return cs.MultistageCheckpointSchedule(steps, int(in_ram), int(on_disk))
    raise ValueError(f"schedule must be 'all', ('revolve', s) or ('multistage', s_in_memory, s_on_disk), "
                     f"got {spec!r}")


def _count(name: str, value) -> int:
    if not is_int(value) or value < 1:
        raise ValueError(f"{name} must be an int >= 1, got {value!r}")
    return int(value)


class _Store:
    """Kept states by step index, in memory or as .npy files in a private directory (per rank)."""

    def __init__(self, disk_dir: str | None, rank: int):
        self.memory: dict = {}
        self._disk: dict = {}
        self.disk_dir, self.rank, self._tmp = disk_dir, rank, None

    def put(self, storage, key, value: np.ndarray) -> None:
        if storage != cs.StorageType.DISK:
            self.memory[key] = value
            return
        if self._tmp is None:
            self._tmp = tempfile.TemporaryDirectory(prefix="fempdl-rollout-", dir=self.disk_dir)
        path = os.path.join(self._tmp.name, f"{key}.rank{self.rank}.bin")
        value = np.ascontiguousarray(value)
        # Raw bytes through Python's file object, whose write and close raise on a short write (a full disk,
        # a file-size limit); numpy's tofile, under np.save, can leave a truncated file without an error.
        try:
            with open(path, "wb") as file:
                file.write(memoryview(value).cast("B"))
        except OSError as err:
            raise OSError(err.errno, f"a multistage rollout could not write its state of step {key} to {path} "
                          f"({err.strerror}: a full disk or a file-size limit); free space there, give the Rollout "
                          "another disk_dir, or keep more snapshots in memory") from None
        self._disk[key] = (path, value.shape, value.dtype)

    def take(self, storage, key, *, keep: bool) -> np.ndarray:
        if storage != cs.StorageType.DISK:
            return self.memory[key] if keep else self.memory.pop(key)
        path, shape, dtype = self._disk[key]
        expected = int(np.prod(shape)) * np.dtype(dtype).itemsize
        size = os.path.getsize(path) if os.path.isfile(path) else -1
        if size != expected:
            raise OSError(f"the state of step {key} a multistage rollout wrote to {path} has "
                          f"{'gone' if size < 0 else f'{size} bytes'} where {expected} were written: another "
                          "process changed its disk_dir; give the Rollout a private disk_dir")
        value = np.fromfile(path, dtype=dtype).reshape(shape)
        if not keep:
            os.remove(path)
            del self._disk[key]
        return value

    @property
    def on_disk(self) -> int:
        return len(self._disk)

    def close(self) -> None:
        if self._tmp is not None:
            self._tmp.cleanup()
            self._tmp = None


class CheckpointedRollout:
    """One rollout call under the schedule ``spec`` (:func:`make_schedule`): :meth:`forward` returns the
    output states, :meth:`backward` the gradients. ``run(k, u, first)`` advances u_k to u_{k+1} ((B, n)
    arrays; ``first``: the first sweep); ``adjoint(k, u_k, u_k1, lam)`` returns (lam_k, {control: dJ/dm_k})
    for step k."""

    def __init__(self, spec, steps: int, run, adjoint, outputs: list, disk_dir: str | None, rank: int):
        self._spec, self._schedule = spec, make_schedule(spec, steps)
        self._actions = iter(self._schedule)
        self._steps, self._run, self._adjoint, self._outputs = steps, run, adjoint, outputs
        self._ics = _Store(disk_dir, rank)
        self._deps: dict = {}                     # step k -> (u_k, u_k+1): shared arrays, counted once
        self._dep_arrays: dict = {}               # id -> pairs of _deps holding that array: O(1) per step
        self._swept = 0                           # steps the forward sweep ran
        # (k, u_k) of the step reversed last: u_k is the state step k - 1 makes, which a schedule's run of
        # that step (to keep its adjoint dependencies) would compute again, bit for bit.
        self._reversed: tuple | None = None
        self.stats = ScheduleStats()
        #: Whether :meth:`backward` ran: the schedule's actions are spent, a second backward needs a new sweep.
        self.spent = False

    def again(self, run) -> CheckpointedRollout:
        """A new rollout on the same schedule and counters whose steps run by ``run`` (a second backward)."""
        other = CheckpointedRollout(self._spec, self._steps, run, self._adjoint, self._outputs, self._ics.disk_dir,
                                    self._ics.rank)
        other.stats = self.stats
        return other

    def forward(self, initial: np.ndarray, first: bool = True) -> list:
        """The forward sweep from u_0; ``first=False``: a sweep run again for a second backward (its steps
        counted as recomputed)."""
        kept = {0: initial} if 0 in self._outputs else {}
        u = initial
        for action in self._actions:
            if isinstance(action, cs.EndForward):
                break
            u = self._act(action, u, kept, first=first)
            if self._schedule.max_n is None and self._swept == self._steps:
                self._schedule.finalize(self._steps)
        self._work = u
        return [kept[i] for i in self._outputs] if first else []

    def backward(self, output_grads: dict) -> tuple:
        """``output_grads``: state index -> dJ/du_i (B, n); returns (dJ/du_0, [per-step control grads])."""
        lam, controls = None, {}
        u = self._work
        self.spent = True
        try:
            for action in self._actions:
                if isinstance(action, cs.EndReverse):
                    break
                if isinstance(action, cs.Reverse):
                    for k in range(action.n1 - 1, action.n0 - 1, -1):
                        uk, uk1 = self._deps[k]
                        lam = _added(lam, output_grads.get(k + 1))
                        if lam is None:
                            lam = np.zeros_like(uk1)
                        lam, controls[k] = self._adjoint(k, uk, uk1, lam)
                        self.stats.adjoint_steps += 1
                        self._reversed = (k, uk)
                        if action.clear_adj_deps:
                            self._set_deps(k, None)
                else:
                    u = self._act(action, u, None, first=False)
        finally:
            self._ics.close()
        return _added(lam, output_grads.get(0)), controls

    def _act(self, action, u: np.ndarray, kept: dict | None, first: bool) -> np.ndarray:
        if isinstance(action, cs.Forward):
            for k in range(action.n0, min(action.n1, self._steps)):
                if k == action.n0 and action.write_ics:
                    self._ics.put(action.storage, action.n0, u)
                if not first and self._reversed is not None and self._reversed[0] == k + 1:
                    u_next = self._reversed[1]      # in hand since the last reversal: not run again
                    self.stats.reused += 1
                else:
                    u_next = self._run(k, u, first)
                    if first:
                        self.stats.steps += 1
                    else:
                        self.stats.recomputed += 1
                if self._swept < self._steps and k == self._swept:
                    self._swept += 1
                if first and kept is not None and k + 1 in self._outputs:
                    kept[k + 1] = u_next
                if action.write_adj_deps:
                    self._set_deps(k, (u, u_next))
                u = u_next
                self._count()
            return u
        if isinstance(action, (cs.Copy, cs.Move)):
            if action.to_storage != cs.StorageType.WORK:
                raise NotImplementedError(f"checkpoint action {action!r}: states move into working memory only")
            return self._ics.take(action.from_storage, action.n, keep=isinstance(action, cs.Copy))
        raise NotImplementedError(f"checkpoint action {action!r} is not one a rollout runs")

    def _set_deps(self, k: int, pair: tuple | None) -> None:
        """Keep (or, ``None``, free) step k's adjoint dependencies, counting the distinct arrays held."""
        for a in self._deps.pop(k, ()):
            self._dep_arrays[id(a)] -= 1
            if not self._dep_arrays[id(a)]:
                del self._dep_arrays[id(a)]
        if pair is not None:
            self._deps[k] = pair
            for a in pair:
                self._dep_arrays[id(a)] = self._dep_arrays.get(id(a), 0) + 1

    def _count(self) -> None:
        """The most distinct states held so far: O(snapshots in memory) a step, not O(steps kept)."""
        others = {id(a) for a in self._ics.memory.values()}
        if self._reversed is not None:
            others.add(id(self._reversed[1]))
        held = len(self._dep_arrays) + len(others - self._dep_arrays.keys())
        self.stats.most_in_memory = max(self.stats.most_in_memory, held)
        self.stats.most_on_disk = max(self.stats.most_on_disk, self._ics.on_disk)


def _added(a, b):
    if b is None:
        return a
    return b.copy() if a is None else a + b


class StatelessRollout:
    """The rollout of a step whose adjoint reads no state (module docstring), with
    :class:`CheckpointedRollout`'s interface: the forward sweep keeps only the output states, the
    backward runs the N adjoints in reverse and runs no step again, whatever the schedule asked; a
    second backward needs no sweep. ``adjoint(k, u_k, u_k+1, lam)`` gets zeros for the states."""

    def __init__(self, steps: int, run, adjoint, outputs: list):
        self._steps, self._run, self._adjoint, self._outputs = steps, run, adjoint, outputs
        self.stats = ScheduleStats()
        self.spent = False

    def again(self, run) -> StatelessRollout:
        other = StatelessRollout(self._steps, run, self._adjoint, self._outputs)
        other.stats, other._zeros = self.stats, self._zeros
        return other

    def forward(self, initial: np.ndarray, first: bool = True) -> list:
        self._zeros = np.broadcast_to(np.zeros((), dtype=initial.dtype), initial.shape)
        if not first:
            return []                 # a second backward: the adjoints read no state
        kept = {0: initial} if 0 in self._outputs else {}
        u = initial
        for k in range(self._steps):
            u = self._run(k, u, first)
            self.stats.steps += 1
            if k + 1 in self._outputs:
                kept[k + 1] = u
        self.stats.most_in_memory = max(self.stats.most_in_memory, 2)      # (u_k, u_k+1) at a time
        return [kept[i] for i in self._outputs]

    def backward(self, output_grads: dict) -> tuple:
        lam, controls = None, {}
        self.spent = True
        for k in range(self._steps - 1, -1, -1):
            lam = _added(lam, output_grads.get(k + 1))
            if lam is None:
                lam = np.zeros(self._zeros.shape)
            lam, controls[k] = self._adjoint(k, self._zeros, self._zeros, lam)
            self.stats.adjoint_steps += 1
        return _added(lam, output_grads.get(0)), controls
