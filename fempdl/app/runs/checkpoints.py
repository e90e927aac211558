"""Run files: atomic writes with the user's umask, and checkpoints that load without running code.

A checkpoint is loaded with ``torch.load(..., weights_only=True)``: its
unpickler rebuilds tensors, dicts, lists, tuples, strings and numbers, and
refuses any other object, so a tampered or foreign ``checkpoint.pt`` can fail
to load but cannot execute anything. Everything saved is therefore a tensor
or a plain value: :func:`plain` converts numpy scalars and arrays and refuses
anything else, and the RNG states are stored as lists and ints
(:func:`rng_state`).

:func:`save` keeps the checkpoint it replaces as ``checkpoint.prev.pt`` (a
hard link, or a copy, so ``checkpoint.pt`` exists at every moment), and :func:`load`
turns every way a file can be unreadable (truncated, empty, not a zip, not
written by fempdl, missing keys) into one :class:`CheckpointError` that names
the file and says what to do.

Files are written to a temporary file beside the target (``.<name>.<random>.tmp``,
created with mode 0666 so the umask applies, as for any file the user
creates) and moved into place with ``os.replace``; a run
killed mid-write leaves such a temporary file, which :func:`remove_stale_temporaries`
deletes on the next start.
"""
from __future__ import annotations

import os
import pickle
import random
import re
import secrets
import shutil
import zipfile
from pathlib import Path
from typing import Callable

import numpy as np
import torch

__all__ = ["CHECKPOINT", "PREVIOUS", "CheckpointError", "write_atomically", "save", "load", "plain",
           "rng_state", "restore_rng", "remove_stale_temporaries"]

CHECKPOINT = "checkpoint.pt"
PREVIOUS = "checkpoint.prev.pt"
_TEMP_SUFFIX = ".tmp"
# Keys every checkpoint written by fempdl holds.
REQUIRED_KEYS = ("epoch", "rows", "elapsed", "model", "optimizer", "scheduler", "prdp", "k",
                 "layer_stats_by_rank", "rng", "fingerprint")


class CheckpointError(RuntimeError):
    """A checkpoint file is unreadable, incomplete, or holds something other than tensors and plain values."""


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(file_path)`` on a temporary file next to ``path``, then move it into place.

    The temporary file is created with mode 0666 minus the umask (not
    mkstemp's 0600) and removed if ``write`` fails. A killed process leaves
    the old file or the new one, never a mix; the file is not fsync'ed (that
    guards against power loss only, and costs about 7 ms per file here, which
    per epoch of a fast scene is more than the epoch)."""
    path = Path(path)
    while True:
        tmp = path.parent / f".{path.name}.{secrets.token_hex(4)}{_TEMP_SUFFIX}"
        try:
            fd = os.open(tmp, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            break
        except FileExistsError:
            continue
    os.close(fd)
    try:
        write(tmp)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def remove_stale_temporaries(directory: Path) -> list[Path]:
    """Delete the temporary files an interrupted write left in ``directory``; returns them.

    Call it only while holding the directory's run lock: a temporary file
    of a live writer would otherwise be removed under it. Files of the
    older ``mkstemp`` naming (``.<name>.<8 characters>``, empty after a
    kill) are removed too."""
    removed = []
    for entry in Path(directory).iterdir():
        name = entry.name
        if not (name.startswith(".") and entry.is_file()):
            continue
        ours = name.endswith(_TEMP_SUFFIX) and name.count(".") >= 3
        legacy = any(name.startswith(f".{target}.") and len(name) == len(target) + 10
                     for target in (CHECKPOINT, "metrics.json", "metrics.csv")) and entry.stat().st_size == 0
        if ours or legacy:
            entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed


def plain(value, where: str = "checkpoint"):
    """``value`` with numpy scalars and arrays turned into Python numbers and tensors.

    Tensors, str, int, float, bool, None and dicts, lists and tuples of them
    pass; anything else raises TypeError naming where it sits, so that a
    checkpoint is never written that ``weights_only`` loading would refuse."""
    if value is None or isinstance(value, (bool, int, float, str, torch.Tensor)):
        return value
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.array(value))
    if isinstance(value, dict):
        return {key: plain(item, f"{where}[{key!r}]") for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(plain(item, f"{where}[{i}]") for i, item in enumerate(value))
    raise TypeError(f"{where} is a {type(value).__name__}; a checkpoint holds only tensors and plain values "
                    "(numbers, strings, lists, dicts): convert it in the object's state_dict")


def rng_state(shuffle: torch.Generator) -> dict:
    """The torch, numpy and Python RNG states and the generator ``shuffle``'s, as tensors and plain values."""
    kind, keys, pos, has_gauss, cached = np.random.get_state()
    version, words, gauss = random.getstate()
    return {"torch": torch.get_rng_state(), "shuffle": shuffle.get_state(),
            "numpy": {"kind": str(kind), "keys": [int(k) for k in keys], "pos": int(pos),
                      "has_gauss": int(has_gauss), "cached_gaussian": float(cached)},
            "python": {"version": int(version), "state": [int(w) for w in words],
                       "gauss": None if gauss is None else float(gauss)}}


def restore_rng(state: dict, shuffle: torch.Generator) -> None:
    """Set the RNGs from :func:`rng_state`'s dict."""
    torch.set_rng_state(state["torch"])
    shuffle.set_state(state["shuffle"])
    n = state["numpy"]
    np.random.set_state((n["kind"], np.array(n["keys"], dtype=np.uint32), n["pos"], n["has_gauss"],
                         n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["state"]), p["gauss"]))


def save(directory: Path, state: dict) -> Path:
    """Write ``state`` (made :func:`plain`) as ``directory/checkpoint.pt``; the previous one becomes
    ``checkpoint.prev.pt``. Returns the path."""
    directory = Path(directory)
    path, previous = directory / CHECKPOINT, directory / PREVIOUS
    state = plain(state)
    if path.exists():
        # A hard link (then an atomic rename onto checkpoint.prev.pt): checkpoint.pt never goes missing.
        link = directory / f".{PREVIOUS}.{secrets.token_hex(4)}{_TEMP_SUFFIX}"
        try:
            try:
                os.link(path, link)
            except OSError:          # a file system without hard links: a copy
                shutil.copyfile(path, link)
            os.replace(link, previous)
        except OSError:
            link.unlink(missing_ok=True)
    try:
        write_atomically(path, lambda p: torch.save(state, p))
    except RuntimeError as err:     # torch's writer reports a failed write (a full disk) as "iostream error"
        raise CheckpointError(f"cannot write the checkpoint {str(path)!r} ({str(err).splitlines()[0]}); is the "
                              "disk full? Free some space and continue the run with --resume") from None
    return path


def _refused_object(err: Exception) -> str:
    """What torch's weights-only unpickler refused, e.g. ``"GLOBAL posix.system"``, from its message."""
    found = re.search(r"(GLOBAL [\w.]+)", str(err))
    return f"it refers to {found.group(1)}" if found else type(err).__name__


def load(path: Path) -> dict:
    """The checkpoint at ``path``, loaded with ``weights_only=True`` (nothing in it is executed).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: the file is unreadable or incomplete, holds objects
            other than tensors and plain values, or lacks keys fempdl writes.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint {str(path)!r}")
    previous = path.parent / PREVIOUS
    remedy = ("start the run afresh (fempdl run ... --overwrite, or without resume in Python)"
              + (f", or restore the previous checkpoint: mv {previous} {path}" if previous.exists() and
                 previous.resolve() != path.resolve() else ""))
    try:
        state = torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        raise CheckpointError(f"checkpoint {str(path)!r} holds objects other than tensors and plain values "
                              f"({_refused_object(err)}); it was not written by this version of fempdl and is "
                              f"not loaded, since unpickling objects can run code. To continue: {remedy}") from None
    except (EOFError, OSError, RuntimeError, ValueError, zipfile.BadZipFile, KeyError, IndexError) as err:
        raise CheckpointError(f"checkpoint {str(path)!r} is unreadable or incomplete "
                              f"({type(err).__name__}: {str(err).splitlines()[0] if str(err) else ''}); "
                              f"to continue: {remedy}") from None
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {str(path)!r} holds a {type(state).__name__}, not a fempdl "
                              f"checkpoint; to continue: {remedy}")
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CheckpointError(f"checkpoint {str(path)!r} is incomplete or was written by an older fempdl "
                              f"(missing {missing}); to continue: {remedy}")
    wrong = _malformed(state)
    if wrong:
        raise CheckpointError(f"checkpoint {str(path)!r} is malformed ({wrong}); it was not written by fempdl "
                              f"or was edited since. To continue: {remedy}")
    return state


def _malformed(state: dict) -> str | None:
    """What is wrong with the plain values of a loaded checkpoint (None: nothing found)."""
    def whole(value, least=0):
        return isinstance(value, int) and not isinstance(value, bool) and value >= least

    def seconds(value):
        return isinstance(value, (int, float)) and not isinstance(value, bool) and 0.0 <= value < float("inf")

    epoch, rows = state["epoch"], state["rows"]
    if not whole(epoch):
        return f"epoch {epoch!r} is not a whole number >= 0"
    if not isinstance(rows, list) or len(rows) != epoch + 1:
        return f"it holds {len(rows) if isinstance(rows, list) else type(rows).__name__} metric rows for {epoch + 1} epochs"
    if any(not isinstance(row, dict) or row.get("epoch") != i for i, row in enumerate(rows)):
        return "its metric rows are not numbered 0, 1, ... in order"
    if not seconds(state["elapsed"]) or not seconds(state.get("train_time", 0.0)):
        return f"elapsed {state['elapsed']!r} or train_time {state.get('train_time')!r} is not a time in seconds"
    if state["k"] is not None and not whole(state["k"], 1):
        return f"k {state['k']!r} is not an iteration cap >= 1"
    by_rank = state["layer_stats_by_rank"]
    if not isinstance(by_rank, list) or not by_rank or not all(isinstance(r, list) for r in by_rank):
        return "layer_stats_by_rank is not one list per rank"
    for key in ("model", "optimizer", "rng", "fingerprint"):
        if not isinstance(state[key], dict):
            return f"{key} is a {type(state[key]).__name__}, not a dict"
    return None
