"""What fempdl wrote into a directory: the record ``.fempdl-record.json``, atomic writes, and reading files safely.

A file's name does not tell who wrote it: your own ``metrics.csv`` or
``time_split.png`` looks like a run's. So before fempdl writes a file into a
directory it adds the name to that directory's record (:func:`record`;
:func:`write_recorded` records and writes), and only recorded names count as
fempdl's (:mod:`fempdl.app.runs.rundir` decides from them what holds a run and
what is yours). The record also keeps what the command trains there
(:func:`record_command`), which a ``--resume`` compares with what it is asked.

The record is read as a regular file of bounded size and never through a
symbolic link; one that cannot be read records nothing, so the directory's
files then count as yours (the safe side: a run needs ``overwrite`` to write
there); one that is a directory can be neither read nor replaced, so it is
refused (:class:`RunDirectoryError`) wherever it is read. Files are written to
a temporary file beside the target (``.<name>.<8 hex digits>.tmp``, mode 0666
so the umask applies) and moved into place with ``os.replace``, which replaces
a symbolic link itself, never the file it points to. A write that fails names
the file it was writing (not its temporary file), and
:func:`size_limit_advice` tells a file size limit from a full disk.
"""
from __future__ import annotations

import errno
import json
import os
import re
import resource
import secrets
import stat
from collections.abc import Callable
from pathlib import Path

from fempdl.core.resources import format_bytes

__all__ = ["RECORD", "RunDirectoryError", "write_atomically", "write_recorded", "record", "recorded", "record_command",
           "command_of", "temporary_path", "is_temporary", "kind", "file_size_limit", "size_limit_advice"]

RECORD = ".fempdl-record.json"
# Far more than the names of the files fempdl writes into one directory; a larger file is not its record.
_MAX_RECORD_BYTES = 1 << 20
_TEMP_SUFFIX = ".tmp"
# ``.<name>.<8 hex digits>.tmp``: what temporary_path gives, and nothing a user is likely to name so.
_TEMPORARY = re.compile(r"\..+\.[0-9a-f]{8}\.tmp")
_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a named pipe"),
          (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))


class RunDirectoryError(RuntimeError):
    """An output directory is in use by another run, or holds a run this one would replace.

    (Defined here, where the record is read, and re-exported by :mod:`fempdl.app.runs.rundir`.)"""


def temporary_path(path: Path) -> Path:
    """A fresh name for a temporary file beside ``path`` (:func:`is_temporary` knows it)."""
    path = Path(path)
    return path.parent / f".{path.name}.{secrets.token_hex(4)}{_TEMP_SUFFIX}"


def is_temporary(name: str) -> bool:
    """Whether ``name`` is that of a temporary file :func:`temporary_path` gives."""
    return _TEMPORARY.fullmatch(name) is not None


def kind(mode: int) -> str:
    """What a file of ``st_mode`` ``mode`` is, for messages: "a regular file", "a directory", ..."""
    return next((name for test, name in _KINDS if test(mode)), "a regular file" if stat.S_ISREG(mode) else
                "a special file")


def write_atomically(path: Path, write: Callable[[Path], None]) -> None:
    """Call ``write(file_path)`` on a temporary file next to ``path``, then move it into place.

    The temporary file is created with mode 0666 minus the umask (not
    mkstemp's 0600) and removed if ``write`` fails. A killed process leaves
    the old file or the new one, never a mix; the file is not fsync'ed (that
    guards against power loss only, and costs about 7 ms per file here, which
    per epoch of a fast scene is more than the epoch)."""
    path = Path(path)
    tmp = None
    try:
        while True:
            tmp = temporary_path(path)
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
    except OSError as err:
        # A write error names no file ("[Errno 28] No space left on device") or the temporary one:
        # name the file the user knows instead.
        if err.errno is None or (err.filename is not None and str(err.filename) != str(tmp)):
            raise
        raise OSError(err.errno, err.strerror, str(path)) from err


def file_size_limit() -> int | None:
    """The most bytes this process may write into one file (``ulimit -f``), or None when unlimited."""
    soft, _ = resource.getrlimit(resource.RLIMIT_FSIZE)
    return None if soft == resource.RLIM_INFINITY else soft


def size_limit_advice(err: OSError) -> str | None:
    """"raise the file size limit (ulimit -f, now 1.0 MiB)" when a write may have failed for ``err``
    because of that limit (EFBIG, or no errno, which torch's writer reports, while a limit is set)."""
    limit = file_size_limit()
    if limit is None or err.errno not in (errno.EFBIG, None):
        return None
    return f"raise the file size limit (ulimit -f, now {format_bytes(limit)})"


def write_recorded(path: Path, write: Callable[[Path], None]) -> None:
    """:func:`record` ``path``'s name in its directory, then :func:`write_atomically` it: a file of the
    run's outputs. Recorded first, so that a file in place is always one the record names."""
    path = Path(path)
    record(path.parent, path.name)
    write_atomically(path, write)


def recorded(directory: Path) -> frozenset[str]:
    """The names fempdl recorded writing into ``directory`` (empty without a readable record)."""
    return frozenset(_read(directory).get("files", ()))


def command_of(directory: Path) -> dict | None:
    """What the command recorded training into ``directory`` (:func:`record_command`), or None."""
    command = _read(directory).get("command")
    return command if isinstance(command, dict) else None


def record(directory: Path, *names: str) -> None:
    """Add ``names`` (files or folders directly in ``directory``) to its record; a no-op when all are there."""
    data = _read(directory)
    files = set(data.get("files", ()))
    if set(names) <= files:
        return
    _write(directory, {**data, "files": sorted(files | set(names))})


def record_command(directory: Path, command: dict) -> None:
    """Keep ``command`` (plain values: what a command trains into ``directory``) in its record."""
    data = _read(directory)
    if data.get("command") != command:
        _write(directory, {"files": [], **data, "command": command})


def _write(directory: Path, data: dict) -> None:
    text = json.dumps({**data, "written_by": "fempdl"}, indent=1)
    write_atomically(Path(directory) / RECORD, lambda p: p.write_text(text))


def _read(directory: Path) -> dict:
    """The record's contents, or {} when there is none or it is not one fempdl wrote."""
    path = Path(directory) / RECORD
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK)
    except OSError:          # none, a symbolic link (ELOOP), unreadable
        return {}
    info = os.fstat(fd)      # before fdopen, which refuses a directory with a message naming only the fd
    if not stat.S_ISREG(info.st_mode) or info.st_size > _MAX_RECORD_BYTES:
        os.close(fd)
        if stat.S_ISDIR(info.st_mode):      # os.replace cannot put a record in its place either
            raise RunDirectoryError(
                f"the record file {str(path)!r} is a directory, not a file fempdl wrote, so it is neither read "
                f"nor replaced; remove it yourself if no run uses {str(directory)!r}, or choose another output "
                "directory (--out)")
        return {}
    with os.fdopen(fd, "rb") as fh:
        raw = fh.read(_MAX_RECORD_BYTES + 1)
    try:
        data = json.loads(raw)
    except ValueError:
        return {}
    if not isinstance(data, dict) or data.get("written_by") != "fempdl":
        return {}
    files = data.get("files", [])
    if not isinstance(files, list) or not all(isinstance(name, str) for name in files):
        return {}
    return data
