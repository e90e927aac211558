"""The training loop: mini-batches, validation, PRDP, metrics files and resumable checkpoints.

:class:`Trainer` runs epochs of ``task.train_step(batch_indices)`` over shuffled
mini-batches, then ``task.validate()``; it steps the PRDP controller (if any)
with the validation metric and writes, after every epoch:

* ``metrics.csv`` and ``metrics.json``: one row per epoch with the train loss
  (mean over the epoch's batches), the validation metric, the K used, the
  cumulative forward and backward inner iterations of the task's layers, the
  cumulative solve time and the total training time;
* ``checkpoint.pt``: model, optimizer, LR scheduler, PRDP state, the layers'
  cumulative counters, the RNG states (torch, numpy, Python, the shuffling
  generator) and the metrics so far.

Every file is written to a temporary file in the same directory and moved into
place with ``os.replace``, so an interrupted run (Ctrl-C, a killed job) leaves
the last completed epoch intact. ``run(resume=True)`` restores all of it and
continues; with the same settings the resumed run produces the same metrics as
an uninterrupted one.

A task provides: ``model`` (nn.Module), ``optimizer``, ``scheduler`` (or None),
``layers`` (the SolveLayers whose iterations are counted), ``train_size``,
``train_step(indices) -> float`` and ``validate() -> float``.
"""
from __future__ import annotations

import csv
import dataclasses
import json
import os
import random
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from fempdl.prdp import PRDP

__all__ = ["Trainer", "nmse", "write_atomically"]

CHECKPOINT = "checkpoint.pt"
METRIC_FIELDS = ("epoch", "train_loss", "val_metric", "k", "forward_iterations", "backward_iterations",
                 "total_iterations", "solve_time", "wall_time")


def nmse(u: torch.Tensor, ref: torch.Tensor) -> torch.Tensor:
    """Normalised MSE, PRDP paper eq. 56: mean_i ||u_i - ref_i||^2 / ||ref_i||^2."""
    return (((u - ref) ** 2).sum(-1) / (ref ** 2).sum(-1)).mean()


def write_atomically(path: Path, write) -> None:
    """Call ``write(file_path)`` on a temporary file next to ``path``, then move it into place."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    os.close(fd)
    try:
        write(Path(tmp))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


@dataclasses.dataclass
class Trainer:
    """Runs a task for ``epochs`` epochs with batch size ``batch``.

    Args:
        task: see the module docstring.
        epochs, batch: the loop's size.
        out_dir: where metrics and the checkpoint go (``None``: nowhere).
        prdp: a controller driving the task's layers, or ``None`` (fixed K).
        seed: seeds the shuffling generator.
        progress: show a tqdm bar with epoch, loss, metric and K.
        stop_after: stop (as if interrupted) after this many epochs of this call.
        stop_at: end training once the validation metric is at or below this
            (the cost to reach a target accuracy is then the iterations used).
    """

    task: object
    epochs: int
    batch: int
    out_dir: Path | None = None
    prdp: PRDP | None = None
    seed: int = 0
    progress: bool = False
    stop_after: int | None = None
    stop_at: float | None = None
    rows: list = dataclasses.field(default_factory=list)

    def __post_init__(self):
        self._shuffle = torch.Generator().manual_seed(self.seed)
        self._elapsed = 0.0
        if self.out_dir is not None:
            self.out_dir = Path(self.out_dir)
            self.out_dir.mkdir(parents=True, exist_ok=True)

    @property
    def k(self) -> int | None:
        return self.task.layers[0].max_it if self.task.layers else None

    def run(self, resume: bool = False) -> list[dict]:
        """Train; returns the metric rows (one per epoch, including resumed ones)."""
        start_epoch = self._restore() if resume else 0
        if self._reached_target():
            return self.rows
        bar = tqdm(range(start_epoch, self.epochs), initial=start_epoch, total=self.epochs,
                   disable=not self.progress, desc="epochs")
        done = 0
        for epoch in bar:
            t0 = time.perf_counter()
            k_used = self.k
            losses = [self.task.train_step(idx) for idx in self._batches()]
            metric = float(self.task.validate())
            if self.prdp is not None:
                self.prdp.step(metric)
            if self.task.scheduler is not None:
                self.task.scheduler.step()
            self._elapsed += time.perf_counter() - t0
            self.rows.append(self._row(epoch, float(np.mean(losses)), metric, k_used))
            bar.set_postfix(loss=f"{self.rows[-1]['train_loss']:.2e}", val=f"{metric:.2e}", K=k_used)
            self._save(epoch)
            done += 1
            if self._reached_target() or (self.stop_after is not None and done >= self.stop_after):
                break
        return self.rows

    def _reached_target(self) -> bool:
        return self.stop_at is not None and bool(self.rows) and self.rows[-1]["val_metric"] <= self.stop_at

    # ------------------------------------------------------------------ steps
    def _batches(self):
        order = torch.randperm(self.task.train_size, generator=self._shuffle)
        for start in range(0, len(order), self.batch):
            yield order[start:start + self.batch]

    def _row(self, epoch: int, loss: float, metric: float, k) -> dict:
        fwd = sum(layer.stats.forward_iterations for layer in self.task.layers)
        bwd = sum(layer.stats.backward_iterations for layer in self.task.layers)
        return {"epoch": epoch, "train_loss": loss, "val_metric": metric, "k": k,
                "forward_iterations": fwd, "backward_iterations": bwd, "total_iterations": fwd + bwd,
                "solve_time": sum(layer.stats.solve_time for layer in self.task.layers),
                "wall_time": self._elapsed}

    # -------------------------------------------------------------- files
    def _save(self, epoch: int) -> None:
        if self.out_dir is None:
            return
        write_atomically(self.out_dir / "metrics.json", lambda p: p.write_text(json.dumps(self.rows, indent=1)))

        def write_csv(p: Path) -> None:
            with p.open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=METRIC_FIELDS)
                writer.writeheader()
                writer.writerows(self.rows)
        write_atomically(self.out_dir / "metrics.csv", write_csv)
        state = {
            "epoch": epoch, "rows": self.rows, "elapsed": self._elapsed,
            "model": self.task.model.state_dict(), "optimizer": self.task.optimizer.state_dict(),
            "scheduler": None if self.task.scheduler is None else self.task.scheduler.state_dict(),
            "prdp": None if self.prdp is None else self.prdp.state_dict(),
            "k": self.k,
            "layer_stats": [dataclasses.asdict(layer.stats) for layer in self.task.layers],
            "rng": {"torch": torch.get_rng_state(), "numpy": np.random.get_state(), "python": random.getstate(),
                    "shuffle": self._shuffle.get_state()},
        }
        write_atomically(self.out_dir / CHECKPOINT, lambda p: torch.save(state, p))

    def _restore(self) -> int:
        """Load the checkpoint; returns the first epoch still to run."""
        path = None if self.out_dir is None else self.out_dir / CHECKPOINT
        if path is None or not path.exists():
            raise FileNotFoundError(f"resume: no checkpoint {CHECKPOINT} in {self.out_dir}; "
                                    "start the run without resume first")
        state = torch.load(path, weights_only=False)
        self.task.model.load_state_dict(state["model"])
        self.task.optimizer.load_state_dict(state["optimizer"])
        if self.task.scheduler is not None:
            self.task.scheduler.load_state_dict(state["scheduler"])
        if self.prdp is not None:
            if state["prdp"] is None:
                raise ValueError(f"{path} was written by a run without PRDP; resume it without --prdp")
            self.prdp.load_state_dict(state["prdp"])
        elif state["k"] is not None:
            for layer in self.task.layers:
                layer.max_it = state["k"]
        for layer, saved in zip(self.task.layers, state["layer_stats"]):
            for key, value in saved.items():
                if key != "last":
                    setattr(layer.stats, key, value)
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        self._shuffle.set_state(state["rng"]["shuffle"])
        self.rows = list(state["rows"])
        self._elapsed = state["elapsed"]
        return state["epoch"] + 1
