"""Where a training run's wall time goes: cumulative seconds per part, adding up to the wall time.

The parts (:data:`TIME_PARTS`):

* ``iterations``, ``setup``, ``assembly``, ``adjoint_operator``: the task's capped layers' own
  counters (:class:`~fempdl.solve.stats.CumulativeStats`: solver iterations, preconditioner
  set-up and factorisations, matrices, right-hand sides and control gradients, an explicit A^T)
  during the training steps;
* ``network``: the rest of the training steps (network forward and backward, the loss,
  autograd, the optimizer step, and the layers' calls up to where their own clock starts);
* ``validation``: the validation pass, whole (network, converged solves, metric);
* ``other``: what remains of each epoch: the layers' conversions and input checks, drawing new
  training data (``start_epoch``), PRDP, the scheduler, agreement checks across ranks, and writing
  the previous epoch's metrics and checkpoint, its log line and progress bar.

The clock runs without a gap from the start of training: an epoch's time is from the end of
the previous epoch's accounting to the end of its own, so the files written after an epoch
count in the next one (the files of the last epoch, written after its row, in none).
"""
from __future__ import annotations

import time

__all__ = ["TIME_PARTS", "TIME_FIELDS", "TimeSplit"]

TIME_PARTS = ("iterations", "setup", "assembly", "adjoint_operator", "network", "validation", "other")
TIME_FIELDS = tuple(f"time_{part}" for part in TIME_PARTS)
# The layers' own counters behind the solver parts of the split.
_LAYER_PARTS = {"iterations": "solve_time", "setup": "setup_time", "assembly": "assembly_time",
                "adjoint_operator": "adjoint_operator_time"}


class TimeSplit:
    """Cumulative seconds per part of :data:`TIME_PARTS` over the epochs of a run of ``task`` (its ``layers``).

    Per epoch: :meth:`start_steps` before the training steps, :meth:`end_steps` after them,
    :meth:`end_validation` after validation, :meth:`end_epoch` when the epoch's work is done
    (returns its seconds). ``seconds`` holds the parts; ``elapsed`` and ``train_time`` the run's
    wall time and the training steps' time (restore all three to resume)."""

    def __init__(self, task):
        self._task = task
        self.seconds = dict.fromkeys(TIME_PARTS, 0.0)
        self.elapsed = self.train_time = 0.0
        self._mark = None

    def start_clock(self) -> None:
        """The run's clock starts (or restarts, on resume) now."""
        self._mark = time.perf_counter()

    def start_steps(self) -> None:
        self._t_steps = time.perf_counter()
        self._before = self._layer_seconds()

    def end_steps(self) -> float:
        """Ends the training steps; returns their seconds."""
        self._t_validation = time.perf_counter()
        self._after = self._layer_seconds()
        self._steps = self._t_validation - self._t_steps
        self.train_time += self._steps
        return self._steps

    def end_validation(self) -> None:
        self._validation = time.perf_counter() - self._t_validation

    def end_epoch(self) -> float:
        """Adds the epoch (since the previous one ended) to the split; returns its seconds."""
        now = time.perf_counter()
        epoch, self._mark = now - self._mark, now
        spent = {part: self._after[key] - self._before[key] for part, key in _LAYER_PARTS.items()}
        spent["network"] = self._steps - (self._after["layer_time"] - self._before["layer_time"])
        spent["validation"] = self._validation
        spent["other"] = epoch - sum(spent.values())     # the parts add up to the epoch exactly
        for part, seconds in spent.items():
            self.seconds[part] += seconds
        self.elapsed += epoch
        return epoch

    def _layer_seconds(self) -> dict:
        """The layers' time counters, summed over the layers."""
        keys = ("layer_time", *_LAYER_PARTS.values())
        return {key: sum(getattr(layer.stats, key) for layer in self._task.layers) for key in keys}
