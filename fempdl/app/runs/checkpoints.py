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
turns every way a file can be unreadable (truncated, empty, not a zip, bytes
that do not match the zip's checksums, not written by fempdl, missing keys,
values out of their types or ranges: :mod:`fempdl.app.runs.checkpoint_values`)
into one :class:`CheckpointError` that names the file and says what to do.

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
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from fempdl.app.runs.checkpoint_values import CheckpointError, malformed

__all__ = ["CHECKPOINT", "PREVIOUS", "CheckpointError", "write_atomically", "save", "load", "plain",
           "rng_state", "restore_rng", "remove_stale_temporaries"]

CHECKPOINT = "checkpoint.pt"
PREVIOUS = "checkpoint.prev.pt"
_TEMP_SUFFIX = ".tmp"
# ``.<name>.<8 hex digits>.tmp``: what write_atomically creates, and nothing a user is likely to name so.
_TEMPORARY = re.compile(r"\..+\.[0-9a-f]{8}\.tmp")
# Keys every checkpoint written by fempdl holds.
REQUIRED_KEYS = ("epoch", "rows", "elapsed", "model", "optimizer", "scheduler", "prdp", "k",
                 "layer_stats_by_rank", "rng", "fingerprint")


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
        if entry.is_file() and not entry.is_symlink() and (_is_temporary(entry.name) or _legacy_temporary(entry)):
            entry.unlink(missing_ok=True)
            removed.append(entry)
    return removed


def _is_temporary(name: str) -> bool:
    """Whether ``name`` is that of a temporary file :func:`write_atomically` creates."""
    return _TEMPORARY.fullmatch(name) is not None


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


def _refused_object(err: Exception) -> str | None:
    """What torch's weights-only unpickler refused, e.g. ``"it refers to GLOBAL posix.system"``, from its
    message; None when it refused no object (the bytes are no pickle at all: a damaged file)."""
    found = re.search(r"(GLOBAL [\w.]+)", str(err))
    return f"it refers to {found.group(1)}" if found else None


def load(path: Path, row_fields: tuple | None = None) -> dict:
    """The checkpoint at ``path``, loaded with ``weights_only=True`` (nothing in it is executed).

    ``row_fields``: the keys a metric row may hold (None: any).

    Raises:
        FileNotFoundError: no such file.
        CheckpointError: the file is unreadable, damaged or incomplete, holds objects
            other than tensors and plain values, lacks keys fempdl writes, or holds
            values out of their types and ranges.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"no checkpoint {str(path)!r}")
    previous = path.parent / PREVIOUS
    remedy = ("start the run afresh (fempdl run ... --overwrite, or without resume in Python)"
              + (f", or restore the previous checkpoint: mv {previous} {path}" if previous.exists() and
                 previous.resolve() != path.resolve() else ""))
    try:
        damaged = _damaged_record(path)
        state = None if damaged else torch.load(path, weights_only=True, map_location="cpu")
    except pickle.UnpicklingError as err:
        if _refused_object(err) is None:
            raise _unreadable(path, err, remedy) from None
        raise CheckpointError(f"checkpoint {str(path)!r} holds objects other than tensors and plain values "
                              f"({_refused_object(err)}); it was not written by this version of fempdl and is "
                              f"not loaded, since unpickling objects can run code. To continue: {remedy}") from None
    except Exception as err:    # a damaged file fails anywhere in the zip reader and unpickler (struct.error, ...)
        raise _unreadable(path, err, remedy) from None
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


def _damaged_record(path: Path) -> str | None:
    """The first part of the checkpoint's zip whose bytes do not match their CRC-32 (torch's reader
    does not compare them, so a changed byte would load as a changed number); None when all match."""
    with zipfile.ZipFile(path) as archive:
        return archive.testzip()


def _unreadable(path: Path, err: BaseException, remedy: str) -> CheckpointError:
    return CheckpointError(f"checkpoint {str(path)!r} is unreadable or incomplete "
                           f"({type(err).__name__}: {_first_line(err)}); to continue: {remedy}")


def _first_line(err: BaseException) -> str:
    text = str(err)
    return text.splitlines()[0] if text else ""
