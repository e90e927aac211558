"""Checkpoints that load without running code, and only from a regular file of a bounded size.

A checkpoint is loaded with ``torch.load(..., weights_only=True)``: its
unpickler rebuilds tensors, dicts, lists, tuples, strings and numbers, and
refuses any other object, so a tampered or foreign ``checkpoint.pt`` can fail
to load but cannot execute anything. Everything saved is therefore a tensor
or a plain value: :func:`plain` converts numpy scalars and arrays and refuses
anything else, and the RNG states are stored as lists and ints
(:func:`rng_state`).

:func:`save` keeps the checkpoint it replaces as ``checkpoint.prev.pt`` (a
hard link, or a copy, so ``checkpoint.pt`` exists at every moment), and :func:`load`
turns every way a file can be unreadable (truncated, empty, not a zip, bytes
that do not match the zip's checksums, not written by fempdl, missing keys,
values out of their types or ranges: :mod:`fempdl.app.runs.checkpoint_values`)
into one :class:`CheckpointError` that names the file and says what to do.
It reads only a regular file (a checkpoint that is a device such as
``/dev/zero`` or a named pipe is refused before a byte is read: read, it grew
the process until the kernel killed it) of at most ``max_bytes``.

Files are written atomically with the user's umask and recorded as fempdl's
(:mod:`fempdl.app.runs.files`); a run killed mid-write leaves a temporary file,
which :func:`remove_stale_temporaries` deletes on the next start.
"""
from __future__ import annotations

import os
import pickle
import random
import re
import shutil
import stat
import zipfile
from pathlib import Path

import numpy as np
import torch

from fempdl.app.runs import files
from fempdl.app.runs.checkpoint_values import CheckpointError, malformed
from fempdl.app.runs.files import is_temporary, write_atomically
from fempdl.core.resources import format_bytes, memory_budget

__all__ = ["CHECKPOINT", "PREVIOUS", "CheckpointError", "write_atomically", "save", "load", "plain",
           "rng_state", "restore_rng", "remove_stale_temporaries", "size_bound"]

CHECKPOINT = "checkpoint.pt"
PREVIOUS = "checkpoint.prev.pt"
# Room in a checkpoint beside its tensors' multiple (size_bound): metric rows, RNG states, counters.
ALLOWANCE = 256 << 20
# Keys every checkpoint written by fempdl holds.
REQUIRED_KEYS = ("epoch", "rows", "elapsed", "model", "optimizer", "scheduler", "prdp", "k",
                 "layer_stats_by_rank", "rng", "fingerprint")


def remove_stale_temporaries(directory: Path) -> list[Path]:
    """Delete the temporary files an interrupted write left in ``directory``; returns them.

    Call it only while holding the directory's run lock: a temporary file
    of a live writer would otherwise be removed under it. Files of the
    older ``mkstemp`` naming (``.<name>.<8 characters>``, empty after a
    kill) are removed too."""
    removed = []
    for entry in Path(directory).iterdir():
        if entry.is_file() and not entry.is_symlink() and (is_temporary(entry.name) or _legacy_temporary(entry)):
            entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed


def _legacy_temporary(entry: Path) -> bool:
    name = entry.name
    return any(name.startswith(f".{target}.") and len(name) == len(target) + 10
               for target in (CHECKPOINT, "metrics.json", "metrics.csv")) and entry.stat().st_size == 0


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
    ``checkpoint.prev.pt``. Returns the path. A failed write raises OSError (torch's writer reports
    one, such as a full disk, as a RuntimeError "iostream error"); the checkpoint before stays."""
    directory = Path(directory)
    path, previous = directory / CHECKPOINT, directory / PREVIOUS
    state = plain(state)
    files.record(directory, CHECKPOINT, PREVIOUS)
    if path.exists():
        # A hard link (then an atomic rename onto checkpoint.prev.pt): checkpoint.pt never goes missing.
        link = files.temporary_path(previous)
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
    except RuntimeError as err:
        raise OSError(str(err).splitlines()[0] if str(err) else type(err).__name__) from None
    return path


def size_bound(*states) -> int:
    """The most bytes a checkpoint of ``states`` (a model's and a task's state dicts) may hold: 16 times
    their tensors (the model, an optimizer's moments, ...) and :data:`ALLOWANCE` for the rest."""
    def nbytes(value) -> int:
        if isinstance(value, torch.Tensor):
            return value.numel() * value.element_size()
        if isinstance(value, dict):
            return sum(nbytes(item) for item in value.values())
        if isinstance(value, (list, tuple)):
            return sum(nbytes(item) for item in value)
        return 0
    return ALLOWANCE + 16 * sum(nbytes(state) for state in states)


def _refused_object(err: Exception) -> str | None:
    """What torch's weights-only unpickler refused, e.g. ``"it refers to GLOBAL posix.system"``, from its
    message; None when it refused no object (the bytes are no pickle at all: a damaged file)."""
    found = re.search(r"(GLOBAL [\w.]+)", str(err))
    return f"it refers to {found.group(1)}" if found else None


def load(path: Path, row_fields: tuple | None = None, max_bytes: int | None = None) -> dict:
    """The checkpoint at ``path``, loaded with ``weights_only=True`` (nothing in it is executed).

    ``row_fields``: the keys a metric row may hold (None: any). ``max_bytes``: the largest file read
    (:func:`size_bound` of the run's model; default half the available memory, beyond which loading
    would endanger the machine).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: the file is no regular file or larger than ``max_bytes``, is unreadable,
            damaged or incomplete, holds objects other than tensors and plain values, lacks keys
            fempdl writes, or holds values out of their types and ranges.
    """
    path = Path(path)
    previous = path.parent / PREVIOUS
    remedy = ("start the run afresh (fempdl run ... --overwrite, or without resume in Python)"
              + (f", or restore the previous checkpoint: mv {previous} {path}" if previous.exists() and
                 previous.resolve() != path.resolve() else ""))
    try:
        # Not blocking: opening a named pipe for reading would wait for a writer.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise FileNotFoundError(f"no checkpoint {str(path)!r}") from None
    # fstat of the file opened, so a link swapped meanwhile cannot slip through; before fdopen, which
    # refuses a directory with a message naming only the descriptor.
    info = os.fstat(fd)
    if not stat.S_ISREG(info.st_mode):
        os.close(fd)
        raise CheckpointError(f"checkpoint {str(path)!r} is {files.kind(info.st_mode)}, not a file fempdl "
                              f"wrote, and is not read; to continue: {remedy}")
    with os.fdopen(fd, "rb") as fh:
        limit = memory_budget() if max_bytes is None else max_bytes
        if info.st_size > limit:
            raise CheckpointError(f"checkpoint {str(path)!r} is {format_bytes(info.st_size)}, more than a "
                                  f"checkpoint of this run can be ({format_bytes(limit)}), and is not read; to "
                                  f"continue: {remedy}")
        state, damaged = _read(fh, path, remedy)
    if damaged:
        raise CheckpointError(f"checkpoint {str(path)!r} is damaged (its part {damaged!r} does not match the "
                              f"checksum written with it); to continue: {remedy}")
    if not isinstance(state, dict):
        raise CheckpointError(f"checkpoint {str(path)!r} holds a {type(state).__name__}, not a fempdl "
                              f"checkpoint; to continue: {remedy}")
    missing = [key for key in REQUIRED_KEYS if key not in state]
    if missing:
        raise CheckpointError(f"checkpoint {str(path)!r} is incomplete or was written by an older fempdl "
                              f"(missing {missing}); to continue: {remedy}")
    try:
        wrong = malformed(state, row_fields)
    except Exception as err:    # a shape the checks did not foresee is as malformed as one they name
        wrong = f"{type(err).__name__}: {_first_line(err)}"
    if wrong:
        raise CheckpointError(f"checkpoint {str(path)!r} is malformed ({wrong}); it was not written by fempdl "
                              f"or was edited or damaged since. To continue: {remedy}")
    return state


def _read(fh, path: Path, remedy: str) -> tuple[object, str | None]:
    """(the unpickled state, None), or (None, the name of a damaged part of the zip)."""
    try:
        damaged = _damaged_record(fh)
        if damaged:
            return None, damaged
        fh.seek(0)
        return torch.load(fh, weights_only=True, map_location="cpu"), None
    except pickle.UnpicklingError as err:
        if _refused_object(err) is None:
            raise _unreadable(path, err, remedy) from None
        raise CheckpointError(f"checkpoint {str(path)!r} holds objects other than tensors and plain values "
                              f"({_refused_object(err)}); it was not written by this version of fempdl and is "
                              f"not loaded, since unpickling objects can run code. To continue: {remedy}") from None
    except Exception as err:    # a damaged file fails anywhere in the zip reader and unpickler (struct.error, ...)
        raise _unreadable(path, err, remedy) from None


def _damaged_record(fh) -> str | None:
    """The first part of the checkpoint's zip whose bytes do not match their CRC-32 (torch's reader
    does not compare them, so a changed byte would load as a changed number); None when all match."""
    with zipfile.ZipFile(fh) as archive:
        return archive.testzip()


def _unreadable(path: Path, err: BaseException, remedy: str) -> CheckpointError:
    return CheckpointError(f"checkpoint {str(path)!r} is unreadable or incomplete "
                           f"({type(err).__name__}: {_first_line(err)}); to continue: {remedy}")


def _first_line(err: BaseException) -> str:
    text = str(err)
    return text.splitlines()[0] if text else ""
