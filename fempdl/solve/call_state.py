"""What a forward call read from shared state, so that its backward reads the same.

A layer's backward runs after its forward, and in between a user's loop may
change what the problem's forms read besides the call's controls: a Constant (a
time stepper that sets ``problem.constants["dt"]`` before each step), a fixed
coefficient Function, a control the call left out (its Function's values), a
boundary value, or the cap (PRDP moves it). The adjoint must be that of the
call that ran, so :class:`CallState` packs those values into one float64 array
at the forward and puts them back around the backward; the array also carries
the call's serial number, under which the system keeps what it saved for that
call's backward (per-sample matrices: :class:`~fempdl.solve.assembly.KeptMatrices`),
so a backward never takes another call's.

Layout of a packed state (local to each rank): the system's :class:`~fempdl.solve.caps.Caps`
(``max_it``, ``inner_max_it``; ``None`` as -1), the call's serial number (0: none), then every read input's
values in :func:`read_inputs` order (a Function's whole local array, ghosts included; a Constant's value).
"""
from __future__ import annotations

import itertools
from contextlib import contextmanager

import numpy as np

from fempdl.core.pointwise_forms import reads_of
from fempdl.solve.assembly import value_of
from fempdl.solve.caps import Caps

__all__ = ["CallState", "read_inputs"]

_NO_CAP = -1.0
_CAP_FIELDS = 2         # Caps.max_it, Caps.inner_max_it
_CALL = _CAP_FIELDS     # the call's serial number
_HEAD = _CAP_FIELDS + 1


def read_inputs(problem) -> tuple:
    """The Constants and Functions the problem's forms (and Dirichlet values) read other than its own work
    Functions, in a fixed order: its control Functions first (a control a call leaves out is read from its
    Function; those a call passes are set per sample and put back after)."""
    forms = (problem.F, problem.J) if hasattr(problem, "F") else (problem.a, problem.L)
    own = {id(getattr(problem, name)) for name in ("u", "lam", "step") if hasattr(problem, name)}
    found: dict = {}
    candidates = [problem.control(n) for n in problem.control_names]
    candidates += [obj for form in forms for obj in reads_of(form)]
    candidates += [bc.g for bc in problem.bcs if hasattr(bc.g, "x") or hasattr(bc.g, "value")]
    for obj in candidates:
        if id(obj) not in own:
            found.setdefault(id(obj), obj)
    return tuple(found.values())


class CallState:
    """Packs and restores a problem's read inputs and a system's caps (``system.caps``).

    Args:
        problem: the layer's Problem or NonlinearProblem.
    """

    def __init__(self, problem):
        self._inputs = read_inputs(problem)
        self._sizes = [np.size(value_of(obj)) for obj in self._inputs]
        self.size = _HEAD + sum(self._sizes)
        self._calls = itertools.count(1)

    def new_call(self) -> int:
        """A serial number no earlier call of this layer had (exact in float64 up to 2^53 calls)."""
        return next(self._calls)

    def pack(self, system, call: int = 0) -> np.ndarray:
        """The state the next solve of ``system`` reads, as one (size,) float64 array; ``call``: the serial
        number of the call it belongs to (:meth:`new_call`)."""
        caps = system.caps
        head = [_NO_CAP if c is None else float(c) for c in (caps.max_it, caps.inner_max_it)] + [float(call)]
        return np.concatenate([np.asarray(head, dtype=np.float64),
                               *(np.asarray(value_of(obj), dtype=np.float64).ravel() for obj in self._inputs)])

    @staticmethod
    def call_of(packed: np.ndarray) -> int | None:
        """The serial number of the call ``packed`` belongs to (None: none)."""
        return int(packed[_CALL]) or None

    @staticmethod
    def with_caps(packed: np.ndarray, caps: Caps) -> np.ndarray:
        """``packed`` with its caps replaced by ``caps`` (an adjoint solved again at a refined cap)."""
        packed = np.array(packed, dtype=np.float64)
        packed[:_CAP_FIELDS] = [_NO_CAP if c is None else float(c) for c in (caps.max_it, caps.inner_max_it)]
        return packed

    @contextmanager
    def restored(self, system, packed: np.ndarray):
        """Within the block, ``system`` and the problem hold the values ``packed`` (from :meth:`pack`); the
        values they held before are put back afterwards. Nothing is written where nothing changed (the
        usual case), so cached matrices and factorisations stay valid; where something did, the system's
        fingerprints see it and reassemble."""
        packed = np.asarray(packed, dtype=np.float64)
        if packed.shape != (self.size,):
            raise ValueError(f"a packed call state has {packed.size} values, this layer's has {self.size}: the "
                             "backward belongs to another layer's forward")
        current = self.pack(system, self.call_of(packed) or 0)
        if np.array_equal(current, packed):
            yield
            return
        self._write(system, packed)
        try:
            yield
        finally:
            self._write(system, current)

    def _write(self, system, packed: np.ndarray) -> None:
        system.caps = Caps(*(None if c == _NO_CAP else int(c) for c in packed[:_CAP_FIELDS]))   # sets what moved
        offset = _HEAD
        for obj, size in zip(self._inputs, self._sizes):
            values = packed[offset:offset + size]
            offset += size
            if hasattr(obj, "x"):
                obj.x.array[:] = values
            elif not np.array_equal(np.asarray(obj.value, dtype=np.float64).ravel(), values):
                _set_constant(obj, values)


def _set_constant(obj, values: np.ndarray) -> None:
    """Write ``values`` into a Constant: in place (a C++ Constant that ``dirichletbc`` made from a number
    has no setter, but its value is a writable view), else by its setter; refuse in one line where neither
    takes."""
    view = obj.value
    if isinstance(view, np.ndarray) and view.flags.writeable:
        view[...] = values.reshape(view.shape)
    else:
        try:
            obj.value = values.reshape(np.shape(view)) if np.ndim(view) else values[0]
        except AttributeError:
            pass
    if not np.array_equal(np.asarray(obj.value, dtype=np.float64).ravel(), values):
        raise ValueError(f"a Constant the forward read ({type(obj).__name__}) changed before its backward and "
                         "cannot be set back: keep it unchanged while a backward is pending")
