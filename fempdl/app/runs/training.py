"""The training loop: mini-batches, validation, PRDP, metrics files and resumable checkpoints.

:class:`Trainer` runs epochs of ``task.train_step`` over shuffled mini-batches
of a task (:class:`fempdl.app.tasks.base.Task` says what a task provides),
validates, steps the PRDP controller, and writes
``metrics.csv``/``metrics.json`` (one row per epoch: losses, K, cumulative
iterations and times, and ``time_<part>`` for each of :data:`TIME_PARTS`
(:mod:`fempdl.app.runs.timesplit`), adding up to ``wall_time``; a task with Newton layers adds
``newton_steps``, forward and unrolled backward, and ``backward_newton_steps``, the latter apart,
its iterations being the inner Krylov ones; rows written before have no ``backward_newton_steps``) and
``checkpoint.pt`` (model, optimizer, scheduler, PRDP, layer counters, each rank's task state, RNG states, rows) after
the last epoch and after every epoch that ends ``checkpoint_every`` seconds or more after the
files were last written (every epoch of a run whose epochs take longer). Every file is written
atomically and recorded as fempdl's (:mod:`fempdl.app.runs.files`), so an interrupted run keeps the
epochs finished up to ``checkpoint_every`` seconds before it; a run with ``resume=True`` continues it
with the same metrics as an uninterrupted run, and refuses a resume whose settings differ
(:meth:`Trainer.fingerprint`). Files that cannot be written end the run with the advice that
fits whether a checkpoint was written yet (:meth:`Trainer._unwritable`).

Under MPI (``parallel="data"`` or ``"mesh"``) every rank runs this loop in
step: data mode shards every batch and the validation samples, mesh mode has
every rank work on a distributed mesh; gradients are summed before every step,
K, the metric and the parameters checked to agree after every epoch, and
rank 0 writes the files.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import json
import logging
from pathlib import Path

from mpi4py import MPI
import numpy as np
import torch
from tqdm import tqdm

from fempdl import __version__
from fempdl.app.runs import checkpoints, files, rundir
from fempdl.app.runs.board import tensorboard_writer
from fempdl.app.runs.checkpoint_values import check_optimizer, check_stats, fitting
from fempdl.app.runs.checkpoints import CHECKPOINT, PREVIOUS, CheckpointError
from fempdl.app.runs.files import write_atomically, write_recorded
from fempdl.app.runs.settings import RunSettings
from fempdl.app.runs.timesplit import TIME_FIELDS, TIME_PARTS, TimeSplit
from fempdl.app.tasks.base import cap_target
from fempdl.core import parallel
from fempdl.methods.prdp import PRDP

__all__ = ["Trainer", "write_atomically", "CheckpointError", "RESUMABLE_CHANGES", "CHECKPOINT", "TIME_PARTS",
           "TIME_FIELDS"]
# Fingerprint keys a resumed run may change: the run's length, which --epochs and an
# equal-training-time extension (fempdl.app.reports.compare) move.
RESUMABLE_CHANGES = ("run.scene.optimizer.epochs", "run.epochs")
# Fingerprint keys that came later, with what a checkpoint written before them ran with.
KEYS_ADDED_LATER = {"run.scene.solver.warm_start": False,      # the inverse task's solves started from zero
                    "run.scene.marker.inputs": "raw",           # the marker network took raw inputs
                    "run.mesh_sha256": rundir.NOT_RECORDED}     # the mesh file's content was not recorded
_log = logging.getLogger(__name__)

METRIC_FIELDS = ("epoch", "train_loss", "val_metric", "k", "forward_iterations", "backward_iterations",
                 "total_iterations", "solve_time", "train_time", "wall_time") + TIME_FIELDS
# Newton layers add their steps (forward and unrolled backward) and the unrolled backward ones apart.
NEWTON_FIELDS = ("newton_steps", "backward_newton_steps")


@dataclasses.dataclass
class Trainer:
    """Runs a task for ``settings.epochs`` epochs of mini-batches of ``batch`` samples.

    Args:
        task: see the module docstring.
        batch: the mini-batch size.
        settings: the run's :class:`~fempdl.app.runs.settings.RunSettings` (``epochs`` given; a
            ``seed`` of ``None`` is 0).
        prdp: a controller driving the task's layers, or ``None`` (fixed K).
        stop_at: end training once the validation metric is at or below this (the cost to reach
            a target accuracy is then the iterations used).
        run_fingerprint: what defines the run beyond the Trainer's own settings (the parsed scene,
            mode, K, ...; plain values). With the batch size, seed, parallel mode, number of ranks
            and the fempdl version it forms the run's fingerprint, stored in the checkpoint: a
            resume whose fingerprint differs is refused (:data:`RESUMABLE_CHANGES` may differ).
    """

    task: object
    batch: int
    settings: RunSettings
    prdp: PRDP | None = None
    stop_at: float | None = None
    run_fingerprint: dict | None = None
    rows: list = dataclasses.field(default_factory=list)

    def __post_init__(self):
        if self.settings.epochs is None:
            raise ValueError("the Trainer needs settings.epochs (the runner takes the scene's)")
        self.settings.check_outputs()
        self.comm = self.settings.ranks
        self.out_dir = self.settings.out_dir
        self.epochs = self.settings.epochs
        self._seed = self.settings.seed or 0
        self._writer = self.comm.rank == 0
        self._shuffle = torch.Generator().manual_seed(self._seed)
        self._clock = TimeSplit(self.task)
        self._saved_at = None         # the clock's elapsed time at the last checkpoint
        self._saved_epoch = None      # the epoch of the last checkpoint written or resumed from
        if self.out_dir is not None and self._writer:
            self.out_dir.mkdir(parents=True, exist_ok=True)
        self._board = None            # opened once the directory is checked and locked (run)

    @property
    def k(self) -> int | None:
        """The cap K in force (:func:`cap_target`)."""
        return cap_target(self.task).k

    def run(self) -> list[dict]:
        """Train; returns the metric rows (one per epoch, including resumed ones).

        The output directory is locked for the run (:class:`fempdl.app.runs.rundir.RunLock`:
        a second run on it is refused); temporary files an interrupted write
        left there are removed; a fresh run (``settings.resume`` False) first removes
        the checkpoints of a run it replaces (those fempdl recorded writing)."""
        resume = self.settings.resume
        refusal = None
        if self.out_dir is not None and self._writer:
            try:
                rundir.check_output_directory(self.out_dir, resume=resume, overwrite=self.settings.overwrite,
                                              nested=False, flags=rundir.PYTHON_FLAGS)
            except rundir.RunDirectoryError as err:
                refusal = str(err)
        if self.comm.bcast(refusal, root=0):       # every rank takes the same branch
            raise rundir.RunDirectoryError(refusal)
        lock = rundir.RunLock(self.out_dir) if self.out_dir is not None and self._writer else None
        if lock is not None:
            lock.acquire()
        try:
            if lock is not None:
                checkpoints.remove_stale_temporaries(self.out_dir)
                if not resume:
                    for name in files.recorded(self.out_dir) & {CHECKPOINT, PREVIOUS}:
                        (self.out_dir / name).unlink(missing_ok=True)
                if self.settings.board_dir is not None:
                    files.record(self.out_dir, self.settings.board_dir.name)
                    self._board = tensorboard_writer(self.settings.board_dir)
            return self._train(resume)
        finally:
            if self._board is not None:
                self._board.flush()
            if lock is not None:
                lock.release()

    def _train(self, resume: bool) -> list[dict]:
        start_epoch = self._restore() if resume else 0
        if self._reached_target():
            return self.rows
        bar = tqdm(range(start_epoch, self.epochs), initial=start_epoch, total=self.epochs,
                   disable=not (self.settings.progress and self._writer), desc="epochs")
        done = 0
        self.comm.barrier()   # the ranks finish building their tasks at different times; time from here
        self._clock.start_clock()
        for epoch in bar:
            if hasattr(self.task, "start_epoch"):
                self.task.start_epoch(epoch)
            k_used = self.k
            self._clock.start_steps()
            losses = [self._train_step(idx) for idx in self._batches()]
            self._clock.end_steps()         # what validation solves belongs to validation
            metric = self._validate()
            self._clock.end_validation()
            if self.prdp is not None:
                self.prdp.step(metric)
            if self.task.scheduler is not None:
                self.task.scheduler.step()
            if self.comm.size > 1:
                parallel.check_identical(self.comm, k=self.k, val_metric=metric)
                parallel.check_same_parameters(self.task.model, self.comm)
            self._clock.end_epoch()
            self.rows.append(self._row(epoch, float(np.mean(losses)), metric, k_used))
            bar.set_postfix(loss=f"{self.rows[-1]['train_loss']:.2e}", val=f"{metric:.2e}", K=k_used)
            done += 1
            last = (epoch + 1 == self.epochs or self._reached_target()
                    or (self.settings.stop_after is not None and done >= self.settings.stop_after))
            self._save(epoch, last)
            self._log_epoch(self.rows[-1])
            self._board_epoch(self.rows[-1])
            if last:
                break
        return self.rows

    def _log_epoch(self, row: dict) -> None:
        """One INFO line per epoch on the "fempdl.app.runs.training" logger (rank 0; the record
        carries ``epoch``, 1-based, so a handler can keep every N-th)."""
        if self._writer and _log.isEnabledFor(logging.INFO):
            run = f"{self.out_dir.name}: " if self.out_dir is not None else ""
            _log.info("%sepoch %d/%d loss %.3e val %.3e K %s iterations %d wall %.1f s", run, row["epoch"] + 1,
                      self.epochs, row["train_loss"], row["val_metric"], row["k"], row["total_iterations"],
                      row["wall_time"], extra={"epoch": row["epoch"] + 1})

    def _board_epoch(self, row: dict) -> None:
        """The row's numbers as TensorBoard scalars at step epoch + 1."""
        if self._board is not None:
            for key, value in row.items():
                if isinstance(value, (int, float)) and not isinstance(value, bool) and key != "epoch":
                    self._board.add_scalar(key, value, row["epoch"] + 1)
            self._board.flush()

    def _reached_target(self) -> bool:
        if not self.rows:
            return False
        last = self.rows[-1]
        return ((self.stop_at is not None and last["val_metric"] <= self.stop_at)
                or (self.settings.stop_at_time is not None and last["train_time"] >= self.settings.stop_at_time))

    # ------------------------------------------------------------------ steps
    def _train_step(self, idx: torch.Tensor) -> float:
        """One optimizer step on the batch ``idx`` (this rank's shard of it in data mode); the batch loss."""
        if self.settings.parallel is None:
            return self.task.train_step(idx)
        share = parallel.shard(idx, self.comm) if self.settings.parallel == "data" else idx
        self.task.optimizer.zero_grad()
        value = 0.0
        if len(share):
            loss = self.task.loss(share)
            if len(share) < len(idx):
                loss = loss * (len(share) / len(idx))
            loss.backward()
            value = loss.item()
        parallel.sum_gradients(self.task.model.parameters(), self.comm)
        self.task.optimizer.step()
        return self.comm.allreduce(value) if self.settings.parallel == "data" else value

    def _validate(self) -> float:
        """The mean validation error over all samples (each rank validates its shard in data mode)."""
        idx = torch.arange(self.task.val_size)
        if self.settings.parallel == "data":
            idx = parallel.shard(idx, self.comm)
        with torch.no_grad():
            total = float(self.task.validation_errors(idx).double().sum()) if len(idx) else 0.0
        if self.settings.parallel == "data":
            total = self.comm.allreduce(total)
        return total / self.task.val_size

    def _batches(self):
        order = torch.randperm(self.task.train_size, generator=self._shuffle)
        for start in range(0, len(order), self.batch):
            yield order[start:start + self.batch]

    def _row(self, epoch: int, loss: float, metric: float, k) -> dict:
        counts = [sum(layer.stats.forward_iterations for layer in self.task.layers),
                  sum(layer.stats.backward_iterations for layer in self.task.layers),
                  sum(layer.stats.solve_time for layer in self.task.layers)]
        if self.settings.parallel == "data":   # every rank solved its own samples: the run's cost is the sum
            counts = [self.comm.allreduce(c) for c in counts]
        fwd, bwd, solve_time = counts
        row = {"epoch": epoch, "train_loss": loss, "val_metric": metric, "k": k,
               "forward_iterations": fwd, "backward_iterations": bwd, "total_iterations": fwd + bwd,
               "solve_time": solve_time, "train_time": self.comm.allreduce(self._clock.train_time, op=MPI.MAX),
               "wall_time": self.comm.allreduce(self._clock.elapsed, op=MPI.MAX),
               **{f"time_{part}": seconds for part, seconds in self._clock.seconds.items()}}
        newton = [layer.stats for layer in self.task.layers if hasattr(layer.stats, "newton_steps")]
        if newton:      # Newton layers: their iterations above are the inner ones; the steps come apart
            steps = [sum(s.newton_steps + s.backward_newton_steps for s in newton),
                     sum(s.backward_newton_steps for s in newton)]
            if self.settings.parallel == "data":
                steps = [self.comm.allreduce(c) for c in steps]
            row["newton_steps"], row["backward_newton_steps"] = steps
        return row

    # -------------------------------------------------------------- files
    def _save(self, epoch: int, last: bool) -> None:
        """Write the files after ``epoch`` if it is the ``last`` of this call or they are due
        (``checkpoint_every``; decided on the row's wall time, the same on every rank)."""
        wall = self.rows[-1]["wall_time"]
        if self.out_dir is None or not (last or wall - (self._saved_at or 0.0) >= self.settings.checkpoint_every):
            return
        self._saved_at = wall
        layer_stats = self.comm.gather([dataclasses.asdict(layer.stats) for layer in self.task.layers])
        task_states = self.comm.gather(getattr(self.task, "state_dict", dict)())
        if not self._writer:
            return
        state = {
            "epoch": epoch, "rows": self.rows, "elapsed": self._clock.elapsed, "train_time": self._clock.train_time,
            "times": dict(self._clock.seconds),
            "model": self.task.model.state_dict(), "optimizer": self.task.optimizer.state_dict(),
            "scheduler": None if self.task.scheduler is None else self.task.scheduler.state_dict(),
            "prdp": None if self.prdp is None else self.prdp.state_dict(),
            "k": self.k,
            "layer_stats_by_rank": layer_stats,
            "task_state_by_rank": task_states,
            "rng": checkpoints.rng_state(self._shuffle),
            "fingerprint": self.fingerprint(),
        }
        try:
            self._write(state)
        except OSError as err:      # no space left, no permission, a read-only file system
            raise self._unwritable(err) from None
        self._saved_epoch = epoch

    def _write(self, state: dict) -> None:
        self._written = []          # what this call replaced, for _unwritable
        write_recorded(self.out_dir / "metrics.json", lambda p: p.write_text(json.dumps(self.rows, indent=1)))
        self._written.append("metrics.json")

        def write_csv(p: Path) -> None:
            with p.open("w", newline="") as fh:
                extra = tuple(key for key in NEWTON_FIELDS if any(key in row for row in self.rows))
                writer = csv.DictWriter(fh, fieldnames=METRIC_FIELDS + extra)
                writer.writeheader()
                writer.writerows(self.rows)
        write_recorded(self.out_dir / "metrics.csv", write_csv)
        self._written.append("metrics.csv")
        checkpoints.save(self.out_dir, state)

    def _unwritable(self, err: OSError) -> rundir.RunDirectoryError:
        """The error for files that could not be written. Before the first checkpoint a resume would
        only start afresh, so the metrics just written without one go (the directory then holds no
        run) and the advice is to start again; after it, a resume continues from the last one."""
        where = f"cannot write the run's files in {str(self.out_dir)!r} ({err.strerror or err})"
        fix = "free some space on its file system or make it writable"
        limit = files.size_limit_advice(err)
        fix = f"{limit}, {fix}" if limit else fix
        if self._saved_epoch is None:
            for name in self._written:
                with contextlib.suppress(OSError):
                    (self.out_dir / name).unlink()
            return rundir.RunDirectoryError(
                f"{where}; no checkpoint was saved, so there is nothing to resume: {fix}, then start the run again")
        return rundir.RunDirectoryError(
            f"{where}; its checkpoint after epoch {self._saved_epoch + 1} is kept: {fix}, then continue the run "
            "with --resume (Python: resume=True)")

    def fingerprint(self) -> dict:
        """What defines this run (``run_fingerprint`` and the Trainer's own), flat; stored in the checkpoint."""
        return rundir.fingerprint(run=self.run_fingerprint or {}, fempdl=__version__,
                                  trainer={"batch": self.batch, "seed": self._seed, "parallel": self.settings.parallel,
                                           "ranks": self.comm.size, "prdp": self.prdp is not None})

    def _restore(self) -> int:
        """Load the checkpoint; returns the first epoch still to run."""
        path = None if self.out_dir is None else self.out_dir / CHECKPOINT
        if path is None or not path.exists():
            raise FileNotFoundError(f"resume: no checkpoint {CHECKPOINT} in {self.out_dir}; "
                                    "start the run without resume first")
        state = checkpoints.load(path, row_fields=METRIC_FIELDS + NEWTON_FIELDS, max_bytes=checkpoints.size_bound(
            self.task.model.state_dict(), getattr(self.task, "state_dict", dict)()))
        changed = rundir.differences(state["fingerprint"], self.fingerprint(), RESUMABLE_CHANGES, KEYS_ADDED_LATER)
        if changed:
            raise rundir.ResumeError(
                f"resume: {path} was written by a different run; changed since: {'; '.join(changed)}. A resume "
                "continues the same run (only the number of epochs may change); to start afresh with these "
                "settings pass --overwrite (Python: resume=False), or choose another output directory")
        done = state["epoch"] + 1
        if done > self.epochs:
            raise rundir.ResumeError(
                f"resume: {path} already holds {done} epochs, more than the {self.epochs} asked for, so there is "
                f"nothing to continue; ask for more (--epochs N with N > {done}) or start afresh (--overwrite)")
        with fitting(path, "model or optimizer state"):
            self.task.model.load_state_dict(state["model"])
            self.task.optimizer.load_state_dict(state["optimizer"])
            if self.task.scheduler is not None:
                self.task.scheduler.load_state_dict(state["scheduler"])
            check_optimizer(self.task.optimizer)
        if self.prdp is not None:
            if state["prdp"] is None:
                raise ValueError(f"{path} was written by a run without PRDP; resume it without --prdp")
            with fitting(path, "PRDP state"):
                self.prdp.load_state_dict(state["prdp"])
        elif state["k"] is not None:
            cap_target(self.task).set_k(state["k"])
        by_rank = state["layer_stats_by_rank"]
        if len(by_rank) != self.comm.size:
            raise ValueError(f"{path} was written by a run on {len(by_rank)} rank(s); "
                             f"resume it on {len(by_rank)}, not {self.comm.size}")
        with fitting(path, "record of the layers' counters"):
            check_stats(by_rank[self.comm.rank], self.task.layers)
        for layer, saved in zip(self.task.layers, by_rank[self.comm.rank]):
            for key, value in saved.items():
                if not key.startswith("last"):     # the last solve's stats (last, last_newton) are not counters
                    setattr(layer.stats, key, value)
        # Checkpoints written before tasks kept state hold none: the task starts from its initial state.
        task_states = state.get("task_state_by_rank", [{}] * self.comm.size)
        if hasattr(self.task, "load_state_dict"):
            with fitting(path, "task state"):
                self.task.load_state_dict(task_states)
        elif any(task_states):
            raise ValueError(f"{path} holds task state that {type(self.task).__name__} cannot take "
                             "(no load_state_dict)")
        checkpoints.restore_rng(state["rng"], self._shuffle)
        self.rows = list(state["rows"])
        self._clock.elapsed = self._saved_at = state["elapsed"]
        self._saved_epoch = state["epoch"]
        if "train_time" not in state and self.settings.stop_at_time is not None:
            raise ValueError(f"{path} was written before fempdl timed training steps (no train_time); it cannot "
                             "be extended to a training time: rerun it without resume")
        self._clock.train_time = state.get("train_time", 0.0)
        self._clock.seconds.update(state.get("times", {}))
        return state["epoch"] + 1
