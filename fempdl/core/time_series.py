"""An XDMF time series written one step at a time, as a long rollout advances (:class:`fempdl.Rollout`'s
``series=``), without keeping the states; the file format and the one-writer lock are
:mod:`fempdl.core.io`'s."""
from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path

import dolfinx.io
import numpy as np

from fempdl.core.checks import check_int
from fempdl.core.io import ENCODINGS, nodal_field, one_writer

__all__ = ["TimeSeries"]


class TimeSeries:
    """An XDMF time series of a problem's solution written one step at a time (a context manager).

    The file opens at the first :meth:`write` (mesh included) and closes with :meth:`close`; every
    rank of a distributed mesh calls both. A mixed solution is written field by field (``u_u``, ``u_p``).
    Times must increase: a write that would repeat one (a second rollout into the same series, or a
    write after :meth:`close`) is refused, or with ``overwrite`` starts the file afresh.

    Args:
        path: the ``.xdmf`` file to create; HDF5 values go beside it (``.h5``). Existing files of
            those names are refused unless ``overwrite``.
        problem: the problem whose solution space the values live in.
        name: the array's name in the file.
        sample: the row written when a value is a batch (B, n).
        every: write the steps 0, every, 2 every, ... (a 5,000-step rollout every 50th) and the last
            state, whatever its step (held until the next write or :meth:`close`).
        encoding: ``"hdf5"`` or ``"ascii"`` (serial only).
        overwrite: replace existing files at ``path``, and start afresh instead of refusing a repeated time.

    Example:
        >>> with TimeSeries("out/heat.xdmf", step.problem, every=10) as series:
        ...     u = rollout(u0, 500, f=f, outputs=[-1], series=series)
    """

    def __init__(self, path, problem, *, name: str = "u", sample: int = 0, every: int = 1,
                 encoding: str = "hdf5", overwrite: bool = False):
        if encoding not in ENCODINGS:
            raise ValueError(f"encoding must be one of {list(ENCODINGS)}, got {encoding!r}")
        check_int("every", every, minimum=1)
        check_int("sample", sample, minimum=0)
        if not isinstance(overwrite, bool):
            raise TypeError(f"overwrite must be True or False, got {overwrite!r}")
        self._given, self.path = str(path), Path(path).with_suffix(".xdmf")
        self.problem, self.name, self.sample, self.every, self._encoding = problem, name, sample, every, encoding
        self.overwrite = overwrite
        self._stack: contextlib.ExitStack | None = None
        self._file = None
        self._spaces: dict = {}
        self._pending = None       # (t, values) of the latest state ``every`` skipped: the last one, so far
        self._last: float | None = None
        self._closed = False       # closed after writing: opening again would replace the file
        #: The times written so far.
        self.times: list = []

    def write(self, step: int, t: float, value, *, last: bool = False) -> None:
        """Write ``value`` ((n,) or (B, n) owned DOF values) at time ``t`` (after the previous one) if
        ``step`` is one to keep or ``last`` (a rollout's final state: written now, the file complete
        without :meth:`close`), else hold it: the series ends with the last state."""
        t = float(t)
        if not math.isfinite(t):
            raise ValueError(f"t must be a finite time, got {t}")
        value = value.detach().cpu().numpy() if hasattr(value, "detach") else np.asarray(value)
        if value.ndim == 2:
            if self.sample >= value.shape[0]:
                raise ValueError(f"TimeSeries(sample={self.sample}) but the batch has {value.shape[0]} samples")
            value = value[self.sample]
        if self._closed or (self._last is not None and t <= self._last):
            self._start_again(t)
        if step % self.every and not last:
            self._pending = (t, np.array(value, dtype=np.float64))     # a copy: callers reuse their buffers
        else:
            self._put(t, value)
            self._pending = None
        self._last = t                # once held or written: a refused write may be given again

    def _start_again(self, t: float) -> None:
        """A write at ``t`` after close or not after ``self._last``: a fresh file if ``overwrite``, else refused."""
        if self.overwrite:
            self._pending = None
            self.close()
            self.times, self._last, self._closed = [], None, False
            return
        if self._closed:
            raise ValueError(f"TimeSeries {str(self.path)!r} is closed and holds times up to t={self._last:g}; "
                             "writing again would replace them: open a new TimeSeries on another path, or pass "
                             "overwrite=True to start the file afresh")
        self._flush()                 # the series so far keeps its last state
        raise ValueError(f"TimeSeries {str(self.path)!r} already holds times up to t={self._last:g}, so a write at "
                         f"t={t:g} would repeat times (a second rollout into one series?); give each rollout its "
                         "own TimeSeries (or path), or pass overwrite=True to start the file afresh")

    def _put(self, t: float, value) -> None:
        if self._file is None:
            self._open()
        p = self.problem
        labels = {f"{self.name}_{field}": field for field in p.fields} if p.fields else {self.name: None}
        for label, field in labels.items():
            self._file.write_function(nodal_field(p.to_function(value, field), label, self._spaces), t)
        self.times.append(t)

    def _flush(self) -> None:
        if self._pending is not None:
            (t, value), self._pending = self._pending, None
            self._put(t, value)

    def _open(self) -> None:
        msh = self.problem.V.mesh
        self.path.parent.mkdir(parents=True, exist_ok=True)
        stack = contextlib.ExitStack()
        try:
            stack.enter_context(one_writer(self.path, msh.comm, "TimeSeries"))
            # Checked under the lock, on one rank: every rank raises, or none.
            refusal = None if self.overwrite else msh.comm.bcast(self._refusal() if msh.comm.rank == 0 else None)
            if refusal:
                raise ValueError(refusal)
            self._file = stack.enter_context(dolfinx.io.XDMFFile(msh.comm, str(self.path), "w",
                                                                 encoding=ENCODINGS[self._encoding]))
            self._file.write_mesh(msh)
        except BaseException:
            stack.close()
            raise
        self._stack = stack

    def _refusal(self) -> str | None:
        """Why opening would replace files, or None."""
        names = [str(self.path)] + ([str(self.path.with_suffix(".h5"))] if self._encoding == "hdf5" else [])
        existing = [repr(name) for name in names if os.path.lexists(name)]
        if not existing:
            return None
        return (f"TimeSeries path {self._given!r} would replace the existing {' and '.join(existing)} (it writes "
                f"{' and '.join(map(repr, names))}); pass overwrite=True to replace, or give another path")

    def close(self) -> None:
        """Write the last state if ``every`` skipped it, and close the file (written steps stay); a second
        call does nothing."""
        try:
            self._flush()
        finally:
            if self._stack is not None:
                self._stack.close()
                self._closed = True
            self._stack = self._file = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
