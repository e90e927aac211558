"""What the values of a loaded checkpoint must be before a resumed run uses them.

A file that loads may still hold values a damaged disk or a hand edit changed: four bytes
overwritten inside the zip change a number, a key or a list's length without the loader
noticing (it keeps no checksums it checks). Every value a resumed run reads is therefore
checked for its type, range and size before anything is set from it, so that such a file
ends in one :class:`~fempdl.app.runs.checkpoints.CheckpointError` naming it, never in an
exception from deep inside torch, numpy or Python's ``random``.

* :func:`malformed`: the values that do not depend on the run (epoch, metric rows, clocks,
  the cap, PRDP's state, the RNG states, the tensors' finiteness); what is wrong, or None.
* :func:`check_stats` and :func:`check_optimizer`: the saved layer counters and optimizer
  state against this run's layers and parameters.
* :func:`fitting`: what taking a checkpoint's state into this run's objects raises becomes
  a CheckpointError naming the file.
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
import random
from pathlib import Path

import numpy as np
import torch

from fempdl.app.runs.timesplit import TIME_PARTS

__all__ = ["CheckpointError", "malformed", "check_stats", "check_optimizer", "fitting", "ROW_KEYS_READ"]

#: The metric row keys a resumed run and its reports read (rows of every fempdl that wrote
#: loadable checkpoints hold them; train_time came later, and a run that needs it says so).
ROW_KEYS_READ = ("epoch", "train_loss", "val_metric", "k", "total_iterations", "wall_time")
_WORDS = 624                 # the Mersenne Twister's state words (numpy's and Python's generators)


class CheckpointError(RuntimeError):
    """A checkpoint file is unreadable, incomplete, or holds something other than tensors and plain values."""


def _whole(value, least: int = 0) -> bool:
    return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _seconds(value) -> bool:
    return _number(value) and 0.0 <= value < math.inf


def malformed(state: dict, row_fields: tuple | None = None) -> str | None:
    """What is wrong with the values of a loaded checkpoint ``state`` (None: nothing found).

    ``row_fields``: the keys a metric row may have (None: any)."""
    checks = (lambda: _rows(state["epoch"], state["rows"], row_fields), lambda: _clocks(state),
              lambda: _containers(state), lambda: _prdp(state["prdp"]), lambda: _rng(state["rng"]),
              lambda: _tensors(state))
    for check in checks:
        wrong = check()
        if wrong:
            return wrong
    return None


def _rows(epoch, rows, fields: tuple | None) -> str | None:
    if not _whole(epoch):
        return f"epoch {epoch!r} is not a whole number >= 0"
    if not isinstance(rows, list) or len(rows) != epoch + 1:
        held = len(rows) if isinstance(rows, list) else type(rows).__name__
        return f"it holds {held} metric rows for {epoch + 1} epochs"
    if any(not isinstance(row, dict) or row.get("epoch") != i for i, row in enumerate(rows)):
        return "its metric rows are not numbered 0, 1, ... in order"
    for i, row in enumerate(rows):
        unknown = sorted(map(repr, set(row) - set(fields))) if fields is not None else []
        missing = [key for key in ROW_KEYS_READ if key not in row]
        odd = [key for key, value in row.items() if value is not None and not _number(value)]
        if unknown or missing or odd:
            return (f"metric row {i} has " + "; ".join(part for part in (
                f"unknown keys {', '.join(unknown)}" if unknown else "", f"no {missing}" if missing else "",
                f"values that are no numbers at {odd}" if odd else "") if part))
    return None


def _clocks(state: dict) -> str | None:
    if not _seconds(state["elapsed"]) or not _seconds(state.get("train_time", 0.0)):
        return f"elapsed {state['elapsed']!r} or train_time {state.get('train_time')!r} is not a time in seconds"
    times = state.get("times", {})
    if not isinstance(times, dict) or any(key not in TIME_PARTS or not _seconds(value) for key, value in times.items()):
        return f"times {times!r} is not seconds per part of {list(TIME_PARTS)}"
    if state["k"] is not None and not _whole(state["k"], 1):
        return f"k {state['k']!r} is not an iteration cap >= 1"
    return None


def _containers(state: dict) -> str | None:
    by_rank = state["layer_stats_by_rank"]
    if not isinstance(by_rank, list) or not by_rank or not all(isinstance(r, list) for r in by_rank):
        return "layer_stats_by_rank is not one list per rank"
    if not all(isinstance(stats, dict) for r in by_rank for stats in r):
        return "layer_stats_by_rank holds an entry that is not a dict of counters"
    tasks = state.get("task_state_by_rank", [{}] * len(by_rank))
    if not isinstance(tasks, list) or len(tasks) != len(by_rank) or not all(isinstance(t, dict) for t in tasks):
        return f"task_state_by_rank is not one dict for each of the {len(by_rank)} rank(s)"
    for key in ("model", "optimizer", "rng", "fingerprint"):
        if not isinstance(state[key], dict):
            return f"{key} is a {type(state[key]).__name__}, not a dict"
    for key in ("scheduler", "prdp"):
        if state[key] is not None and not isinstance(state[key], dict):
            return f"{key} is a {type(state[key]).__name__}, not a dict or None"
    return None


def _prdp(prdp: dict | None) -> str | None:
    if prdp is None:
        return None
    history = prdp.get("history")
    if not _whole(prdp.get("k"), 1) or not isinstance(prdp.get("settings"), dict) or not isinstance(history, list) \
            or not all(isinstance(record, dict) for record in history) \
            or not (prdp.get("checkpoint") is None or _number(prdp.get("checkpoint"))):
        return "prdp is not a PRDP controller's state (k >= 1, checkpoint, history records, settings)"
    return None


def _rng(rng: dict) -> str | None:
    """Whether the RNG states are what :func:`~fempdl.app.runs.checkpoints.rng_state` writes, checked
    by ranges (numpy would wrap a negative word around) and by setting them on scratch generators."""
    numpy_state, python_state = rng.get("numpy"), rng.get("python")
    if not isinstance(numpy_state, dict) or not isinstance(python_state, dict):
        return "rng holds no numpy and python states"
    words, keys = python_state.get("state"), numpy_state.get("keys")
    if not (isinstance(keys, list) and len(keys) == _WORDS and all(_whole(k) and k < 2 ** 32 for k in keys)
            and isinstance(words, list) and len(words) == _WORDS + 1
            and all(_whole(w) and w < 2 ** 32 for w in words[:-1]) and _whole(words[-1]) and words[-1] <= _WORDS
            and _whole(numpy_state.get("pos")) and numpy_state["pos"] <= _WORDS
            and numpy_state.get("has_gauss") in (0, 1) and _number(numpy_state.get("cached_gaussian"))
            and (python_state.get("gauss") is None or _number(python_state["gauss"]))):
        return "rng holds numpy or python generator states out of their ranges"
    try:
        for name in ("torch", "shuffle"):
            torch.Generator().set_state(rng[name])
        np.random.RandomState().set_state((numpy_state["kind"], np.array(keys, dtype=np.uint32),
                                           numpy_state["pos"], numpy_state["has_gauss"],
                                           numpy_state["cached_gaussian"]))
        random.Random().setstate((python_state["version"], tuple(words), python_state["gauss"]))
    except Exception as err:       # what each generator refuses, whatever the generator raises for it
        return f"rng holds a state its generator refuses ({type(err).__name__}: {_first_line(err)})"
    return None


def _tensors(state: dict) -> str | None:
    """Non-finite weights or optimizer moments (a damaged float), which training would only spread."""
    moments = state["optimizer"].get("state")       # a torch optimizer's per-parameter state (HIG has none)
    optimizer_tensors = [value for entry in (moments.values() if isinstance(moments, dict) else ())
                         if isinstance(entry, dict) for value in entry.values()]
    for where, values in (("model", state["model"].values()), ("optimizer", optimizer_tensors)):
        for value in values:
            if where == "model" and not isinstance(value, torch.Tensor):
                return "model holds a value that is no tensor"
            if isinstance(value, torch.Tensor) and value.is_floating_point() and not torch.isfinite(value).all():
                return f"{where} holds NaN or inf values"
    return None


def check_stats(saved: list, layers: list) -> None:
    """Raise ValueError unless a rank's saved layer counters ``saved`` (dicts) fit this run's ``layers``:
    one dict per layer, with keys its stats have and values of their kinds."""
    if len(saved) != len(layers):
        raise ValueError(f"it holds counters of {len(saved)} layer(s), this run has {len(layers)}")
    for i, (counters, layer) in enumerate(zip(saved, layers)):
        fields = {f.name: getattr(layer.stats, f.name) for f in dataclasses.fields(layer.stats)}
        for key, value in counters.items():
            if isinstance(key, str) and key.startswith("last"):   # the last solve's stats, not restored
                continue
            if key not in fields:
                raise ValueError(f"layer {i}'s counters have an unknown key {key!r}")
            if not _like(value, fields[key]):
                raise ValueError(f"layer {i}'s counter {key} is {value!r}, not a count or seconds")


def _like(value, current) -> bool:
    """Whether ``value`` can stand for a counter now holding ``current``: a whole count, finite
    non-negative seconds, or counts by name."""
    if isinstance(current, dict):
        return isinstance(value, dict) and all(isinstance(k, str) and _whole(v) for k, v in value.items())
    if isinstance(current, int):
        return _whole(value)
    return _seconds(value)


def check_optimizer(optimizer) -> None:
    """Raise ValueError for a loaded state tensor of a torch optimizer whose shape is not its
    parameter's (torch's loader does not check, and the next step would fail in its arithmetic).
    Other optimizers (HIG) keep no per-parameter state to check."""
    if not isinstance(optimizer, torch.optim.Optimizer):
        return
    for group in optimizer.param_groups:
        for param in group["params"]:
            for key, value in optimizer.state.get(param, {}).items():
                if isinstance(value, torch.Tensor) and value.dim() and value.shape != param.shape:
                    raise ValueError(f"optimizer state {key!r} has shape {tuple(value.shape)} for a parameter "
                                     f"of shape {tuple(param.shape)}")


@contextlib.contextmanager
def fitting(path: Path, what: str):
    """Run the block that sets this run's ``what`` from the checkpoint at ``path``; whatever it raises
    (torch's and the task's loaders check in their own ways) becomes a CheckpointError naming the file."""
    try:
        yield
    except CheckpointError:
        raise
    except Exception as err:
        raise CheckpointError(f"{path}: its {what} does not fit this run's ({type(err).__name__}: "
                              f"{_first_line(err)}); start afresh (--overwrite) or restore a checkpoint of "
                              "this run") from None


def _first_line(err: BaseException) -> str:
    text = str(err)
    return text.splitlines()[0] if text else ""
