"""Output directories of runs: safe names, one run per directory, and the run's fingerprint.

* :func:`check_slug` and :func:`child`: a name that becomes part of a path
  (a scene's name under ``runs/``) is a slug of letters, digits and ``-_.``
  that is not ``.`` or ``..``, and the path built from it stays inside its
  parent.
* :class:`RunLock`: an exclusive lock on a directory, the file ``.lock``
  holding the owner's host and PID. It is created with ``O_EXCL`` (atomic);
  a lock whose process no longer runs on this host is stale and taken over;
  it is removed when the run ends, also on an exception or Ctrl-C. A second
  run on the same directory is refused with a message naming the owner.
* :func:`fingerprint` and :func:`differences`: what defines a run (the parsed
  scene, the mode, K, the number of ranks, the package version, ...) as a
  flat dict of plain values; a resumed run compares its own with the
  checkpoint's and refuses any difference but the allowed ones (the number
  of epochs, a training-time target).
"""
from __future__ import annotations

import os
import socket
from pathlib import Path

from fempdl.app.runs.checkpoints import CHECKPOINT
from fempdl.app.schema import check_slug

__all__ = ["LOCK", "ResumeError", "RunDirectoryError", "RunLock", "check_slug", "child", "fingerprint", "differences",
           "holds_run"]

LOCK = ".lock"
# Files whose presence means a directory holds a run.
RUN_FILES = (CHECKPOINT, "metrics.csv", "metrics.json")


class RunDirectoryError(RuntimeError):
    """An output directory is in use by another run, or holds a run this one would replace."""


class ResumeError(ValueError):
    """A resume would not continue the run the checkpoint holds (its fingerprint differs)."""


def child(parent: Path, name: str, what: str = "name") -> Path:
    """``parent / name`` for a slug ``name``, checked to lie inside ``parent``."""
    path = Path(parent) / check_slug(name, what)
    if Path(os.path.abspath(path)).parent != Path(os.path.abspath(parent)):
        raise ValueError(f"{what} {name!r} leads outside {str(parent)!r}")
    return path


def holds_run(directory: Path) -> bool:
    """Whether ``directory`` or a directory directly inside it holds run files (a checkpoint or metrics)."""
    directory = Path(directory)
    if not directory.is_dir():
        return False
    candidates = [directory] + [d for d in directory.iterdir() if d.is_dir()]
    return any((d / name).exists() for d in candidates for name in RUN_FILES)


class RunLock:
    """An exclusive lock on ``directory`` for one run (module docstring); a context manager.

    Raises :class:`RunDirectoryError` on entering when another live process
    holds it. Re-entrant within a process: a lock this process already holds
    is not taken again (a command that locks its output directory and then
    trains in it)."""

    _held: set = set()

    def __init__(self, directory: Path):
        self.directory = Path(directory)
        self.path = self.directory / LOCK
        self._mine = False

    def __enter__(self) -> "RunLock":
        self.acquire()
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def acquire(self) -> None:
        key = os.path.abspath(self.path)
        if key in RunLock._held:
            return
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as err:      # a file in the way, no permission, read-only file system
            raise RunDirectoryError(f"cannot use {str(self.directory)!r} as an output directory ({err.strerror}); "
                                    "choose another (--out)") from None
        me = f"{socket.gethostname()} {os.getpid()}\n"
        for _ in range(3):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o666)
            except PermissionError as err:
                raise RunDirectoryError(f"cannot write to {str(self.directory)!r} ({err.strerror}); choose another "
                                        "output directory (--out)") from None
            except FileExistsError:
                owner = self._owner()
                if owner is not None and _alive(*owner):
                    raise RunDirectoryError(
                        f"{str(self.directory)!r} is in use by another run (process {owner[1]} on {owner[0]}, "
                        f"lock file {str(self.path)!r}); wait for it to finish or choose another output "
                        "directory (--out); if that process is not a fempdl run, delete the lock file") from None
                self.path.unlink(missing_ok=True)      # stale: its process is gone
                continue
            with os.fdopen(fd, "w") as fh:
                fh.write(me)
            RunLock._held.add(key)
            self._mine = True
            return
        raise RunDirectoryError(f"could not take the lock {str(self.path)!r}: another process keeps "
                                "creating it; choose another output directory (--out)")

    def release(self) -> None:
        if not self._mine:
            return
        RunLock._held.discard(os.path.abspath(self.path))
        self._mine = False
        owner = self._owner()
        if owner == (socket.gethostname(), os.getpid()):
            self.path.unlink(missing_ok=True)

    def _owner(self) -> tuple[str, int] | None:
        """(host, pid) written in the lock file, or None when it is unreadable (being written, or garbage)."""
        try:
            host, pid = self.path.read_text().split()
            return host, int(pid)
        except (OSError, ValueError):
            return None


def _alive(host: str, pid: int) -> bool:
    """Whether process ``pid`` on ``host`` may still run (a lock from another host is assumed live)."""
    if host != socket.gethostname():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def fingerprint(**parts) -> dict:
    """``parts`` (nested dicts of plain values) flattened to ``{"a.b": value}`` with lists kept as lists."""
    out = {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, dict):
            for key in sorted(value):
                walk(f"{prefix}.{key}" if prefix else str(key), value[key])
        else:
            out[prefix] = list(value) if isinstance(value, tuple) else value

    walk("", parts)
    return out


def differences(saved: dict, current: dict, allowed: tuple = (), absent_means: dict | None = None) -> list[str]:
    """``"key: saved -> now"`` for every key of the two fingerprints that differs and is not ``allowed``.

    ``absent_means``: keys added to the fingerprint later, with the value a run
    written before them had (a checkpoint without the key behaves so)."""
    old = {**(absent_means or {}), **saved}
    keys = sorted(set(saved) | set(current))
    return [f"{key}: {saved.get(key, '<absent>')!r} -> {current.get(key, '<absent>')!r}" for key in keys
            if key not in allowed and old.get(key, "<absent>") != current.get(key, "<absent>")]
