"""Output directories of runs: safe names, one run per directory, and the run's fingerprint.

* :func:`check_slug` and :func:`child`: a name that becomes part of a path
  (a scene's name under ``runs/``) is a slug of letters, digits and ``-_.``
  that is not ``.`` or ``..``, and the path built from it stays inside its
  parent.
* :class:`RunLock`: an exclusive lock on a directory: the kernel's lock
  (``flock``) on the file ``.lock``, which holds the owner's host and PID for
  messages. Two processes acquiring at the same instant cannot both hold it,
  and a process that dies frees it; a lock file written by a live process
  that holds no kernel lock is respected too. It is removed when the run
  ends, also on an exception or Ctrl-C. A second run on the same directory
  is refused with a message naming the owner. A ``.lock`` that is a symbolic
  link or no regular file is refused, never written through or deleted: it
  is not fempdl's, and writing the owner into a link's target would replace
  that file.
* :func:`check_output_directory`: a run writes only into a new or empty
  directory, or into one holding an earlier run when told to resume or
  overwrite it; a directory holding files of the user's needs ``overwrite``,
  which replaces only files of the names fempdl writes and deletes nothing
  else. What is fempdl's is what it recorded writing
  (:mod:`fempdl.app.runs.files`), never a name alone: a folder of your own
  ``metrics.csv`` and ``time_split.png`` holds no run, so ``resume`` does not
  make it writable.
* :func:`fingerprint` and :func:`differences`: what defines a run (the parsed
  scene, the mode, K, the number of ranks, the package version, ...) as a
  flat dict of plain values; a resumed run compares its own with the
  checkpoint's and refuses any difference but the allowed ones (the number
  of epochs, a training-time target).
"""
from __future__ import annotations

import fcntl
import itertools
import os
import socket
import stat
from pathlib import Path

from fempdl.app.runs import files
from fempdl.app.runs.checkpoints import CHECKPOINT
from fempdl.app.runs.files import RunDirectoryError
from fempdl.app.schema import check_slug
from fempdl.core.locks import same_file

__all__ = ["LOCK", "ResumeError", "RunDirectoryError", "RunLock", "check_slug", "child", "fingerprint", "differences",
           "holds_run", "foreign_entries", "check_output_directory", "can_resume", "COMMAND_FLAGS", "PYTHON_FLAGS"]

LOCK = ".lock"
#: In :func:`differences`' ``absent_means``: a checkpoint written before the key existed did not record it.
NOT_RECORDED = object()
# Files whose presence (recorded by fempdl) means a directory holds a run.
RUN_FILES = (CHECKPOINT, "metrics.csv", "metrics.json")
#: How the command and the Python API spell the choices a refusal names.
COMMAND_FLAGS = {"resume": "--resume", "overwrite": "--overwrite", "out": "--out"}
PYTHON_FLAGS = {"resume": "resume=True", "overwrite": "overwrite=True (the command: --overwrite)", "out": "out_dir"}
_NAMES_SHOWN = 3
# How deep folders fempdl recorded nothing in are looked into (a scene's folder, its tradeoff folder,
# that folder's runs), and how many foreign entries are listed at most: a directory of yours is refused
# on its first few, and --out at a large tree must not walk all of it.
_DEPTH = 3
_MOST_LISTED = 1000


class ResumeError(ValueError):
    """A resume would not continue the run the checkpoint holds (its fingerprint differs)."""


def child(parent: Path, name: str, what: str = "name") -> Path:
    """``parent / name`` for a slug ``name``, checked to lie inside ``parent``."""
    path = Path(parent) / check_slug(name, what)
    if Path(os.path.abspath(path)).parent != Path(os.path.abspath(parent)):
        raise ValueError(f"{what} {name!r} leads outside {str(parent)!r}")
    return path


def holds_run(directory: Path, nested: bool = True) -> bool:
    """Whether ``directory`` (or, ``nested``, a directory directly inside it) holds a run: a checkpoint
    or metrics that fempdl recorded writing there."""
    directory = Path(directory)
    if not directory.is_dir():
        return False
    candidates = [directory] + ([d for d in directory.iterdir() if d.is_dir() and not d.is_symlink()]
                                if nested else [])
    return any(_run_in(d) for d in candidates)


def _run_in(directory: Path) -> bool:
    names = files.recorded(directory)
    return any(name in names and (directory / name).exists() for name in RUN_FILES)


def can_resume(directory: Path) -> bool:
    """Whether ``directory`` holds a checkpoint fempdl wrote (a run to continue, not to start afresh)."""
    return CHECKPOINT in files.recorded(directory) and (Path(directory) / CHECKPOINT).exists()


def foreign_entries(directory: Path) -> list[str]:
    """The sorted paths (relative to ``directory``) of the entries fempdl did not write: not recorded in
    their directory (:mod:`fempdl.app.runs.files`), looking into folders it recorded nothing in (a
    scene's run folders beside its ``tradeoff`` folder) a few levels deep, at most
    :data:`_MOST_LISTED`. Hidden names do not count: fempdl's own (its record, lock, temporary files)
    are hidden, and no file it writes could replace one of yours (``.DS_Store``, ``.git``). Empty for
    a new or empty directory."""
    directory = Path(directory)
    if not directory.is_dir():
        return []
    return sorted(itertools.islice(_foreign(directory, _DEPTH, ""), _MOST_LISTED))


def _foreign(directory: Path, depth: int, prefix: str):
    names = files.recorded(directory)
    try:
        entries = sorted(directory.iterdir())
    except OSError:             # unreadable: what it holds is unknown, so it is not fempdl's
        yield prefix.rstrip("/") or "."
        return
    for entry in entries:
        if entry.name.startswith(".") or entry.name in names:
            continue
        if depth > 1 and entry.is_dir() and not entry.is_symlink():
            yield from _foreign(entry, depth - 1, f"{prefix}{entry.name}/")
        else:
            yield f"{prefix}{entry.name}"


def check_output_directory(directory: Path, *, resume: bool, overwrite: bool, nested: bool = True,
                           flags: dict = COMMAND_FLAGS) -> None:
    """Raise :class:`RunDirectoryError` unless runs may write into ``directory``: it is new or empty
    or holds only what fempdl wrote, and when that includes an earlier run (:func:`holds_run`,
    ``nested`` as there) ``resume`` or ``overwrite`` is given; a directory holding other files (the
    user's: a plot of the same name as one fempdl writes would be replaced) needs ``overwrite``,
    also to resume. ``flags`` spell the choices in the message."""
    directory = Path(directory)
    foreign = [] if overwrite else foreign_entries(directory)
    run = holds_run(directory, nested)
    if foreign:
        shown = ", ".join(foreign[:_NAMES_SHOWN]) + (
            "" if len(foreign) <= _NAMES_SHOWN else
            f", ... ({len(foreign)}{'+' if len(foreign) == _MOST_LISTED else ''} entries)")
        if run:
            raise RunDirectoryError(
                f"{str(directory)!r} holds an earlier run and files fempdl did not write ({shown}); move those "
                f"out and pass {flags['resume']} to continue the run, or choose another {flags['out']} "
                f"({flags['overwrite']} would replace the run, and files of yours named as fempdl's)")
        # Run files with no record beside them: the user's, or a run of a fempdl from before the record.
        earlier = any(Path(name).name in RUN_FILES for name in foreign)
        raise RunDirectoryError(
            f"{str(directory)!r} holds no fempdl run but files fempdl did not write ({shown}); runs write into "
            f"a new or empty directory or one of their own: choose another {flags['out']}, or pass "
            f"{flags['overwrite']} to write into it anyway (files named as fempdl's, such as metrics.csv or "
            "time_split.png, are then replaced; nothing else is touched)" + (
                ". A run written by a fempdl older than its record of the files it writes (.fempdl-record.json) "
                "counts as such files: continue it with the version that wrote it" if earlier else ""))
    if run and not (resume or overwrite):
        raise RunDirectoryError(
            f"{str(directory)!r} holds the files of an earlier run; pass {flags['resume']} to continue it, "
            f"{flags['overwrite']} to replace it, or choose another {flags['out']}")


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
        self._fd = None

    def __enter__(self) -> RunLock:
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
        me = (socket.gethostname(), os.getpid())
        for _ in range(3):
            fd = self._open()
            try:
                # The kernel's lock decides, atomically, and frees it when its process dies:
                # two processes acquiring at the same instant cannot both hold it.
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                raise self._in_use(self._owner()) from None
            if not same_file(fd, self.path):     # a holder released (unlinked) it meanwhile: lock the new one
                os.close(fd)
                continue
            owner = _read_owner(fd)
            if owner is not None and owner != me and _alive(*owner):
                os.close(fd)                  # written by a live process that holds no kernel lock
                raise self._in_use(owner)
            try:
                os.ftruncate(fd, 0)
                os.pwrite(fd, f"{me[0]} {me[1]}\n".encode(), 0)
            except OSError as err:            # e.g. no space left on the device
                os.close(fd)
                raise RunDirectoryError(f"cannot write the lock file {str(self.path)!r} ({err.strerror}); free "
                                        "some space or choose another output directory (--out)") from None
            self._fd = fd
            RunLock._held.add(key)
            self._mine = True
            return
        raise RunDirectoryError(f"could not take the lock {str(self.path)!r}: other processes keep taking and "
                                "releasing it; choose another output directory (--out)")

    def release(self) -> None:
        if not self._mine:
            return
        RunLock._held.discard(os.path.abspath(self.path))
        self._mine = False
        # Unlinked while still locked, so no process can lock this file after it left the directory
        # and believe it holds the directory's lock (acquire checks the path still names its file).
        # Only while the path names this very file: whatever took its place is not ours to delete.
        if same_file(self._fd, self.path):
            self.path.unlink(missing_ok=True)
        os.close(self._fd)
        self._fd = None

    def _open(self) -> int:
        """The lock file, created if missing, never through a symbolic link (O_NOFOLLOW: the owner
        written into a link's target would replace that file), and only a regular file."""
        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK, 0o666)
        except OSError as err:
            mode = _mode(self.path)
            if mode is not None and not stat.S_ISREG(mode):       # a link (ELOOP), a directory (EISDIR)
                raise self._not_a_lock(mode) from None
            raise RunDirectoryError(f"cannot write to {str(self.directory)!r} ({err.strerror}); choose another "
                                    "output directory (--out)") from None
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):        # a named pipe or device opens; it is not a lock file
            os.close(fd)
            raise self._not_a_lock(mode)
        return fd

    def _not_a_lock(self, mode: int) -> RunDirectoryError:
        return RunDirectoryError(
            f"the lock file {str(self.path)!r} is {files.kind(mode)}, not a file fempdl created, so it is neither "
            f"written nor deleted; remove it yourself if no run uses {str(self.directory)!r}, or choose another "
            "output directory (--out)")

    def _in_use(self, owner) -> RunDirectoryError:
        who = f"process {owner[1]} on {owner[0]}" if owner else "a process that is starting"
        return RunDirectoryError(
            f"{str(self.directory)!r} is in use by another run ({who}, lock file {str(self.path)!r}); wait for "
            "it to finish or choose another output directory (--out); if that process is not a fempdl run, "
            "delete the lock file")

    def _owner(self) -> tuple[str, int] | None:
        """(host, pid) written in the lock file, or None when it is unreadable (being written, or garbage)."""
        try:
            fd = os.open(self.path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
        except OSError:
            return None
        try:
            return _read_owner(fd) if stat.S_ISREG(os.fstat(fd).st_mode) else None
        except OSError:
            return None
        finally:
            os.close(fd)


def _mode(path: Path) -> int | None:
    """``path``'s own st_mode (of a link, not its target), or None when it does not exist."""
    try:
        return os.lstat(path).st_mode
    except OSError:
        return None


def _read_owner(fd: int) -> tuple[str, int] | None:
    return _parse_owner(os.pread(fd, 4096, 0).decode(errors="replace"))


def _parse_owner(text: str) -> tuple[str, int] | None:
    try:
        host, pid = text.split()
        return host, int(pid)
    except ValueError:
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
    written before them had (a checkpoint without the key behaves so), or
    :data:`NOT_RECORDED` when that value is unknown (such a checkpoint is not checked on the key)."""
    absent_means = absent_means or {}
    old = {**absent_means, **saved}
    keys = sorted(set(saved) | set(current))
    unknown = {key for key, value in absent_means.items() if value is NOT_RECORDED and key not in saved}
    return [f"{key}: {saved.get(key, '<absent>')!r} -> {current.get(key, '<absent>')!r}" for key in keys
            if key not in allowed and key not in unknown and old.get(key, "<absent>") != current.get(key, "<absent>")]
