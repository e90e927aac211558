"""What a forward call read from shared state, so that its backward reads the same.

A layer's backward runs after its forward, and in between a user's loop may
change what the problem's forms read besides the call's controls: a Constant (a
time stepper that sets ``problem.constants["dt"]`` before each step), a fixed
coefficient Function, or the cap (PRDP moves it). The adjoint must be that of
the call that ran, so :class:`CallState` packs those values into one float64
array at the forward and puts them back around the backward.

Layout of a packed state (local to each rank): the system's :class:`~fempdl.solve.caps.Caps`
(``max_it``, ``inner_max_it``; ``None`` as -1), then every read input's values in :func:`read_inputs` order (a
Function's whole local array, ghosts included; a Constant's value).
"""
from __future__ import annotations

from contextlib import contextmanager

import numpy as np

from fempdl.solve.assembly import value_of
from fempdl.solve.caps import Caps

__all__ = ["CallState", "read_inputs"]

_NO_CAP = -1.0
_CAP_FIELDS = 2         # Caps.max_it, Caps.inner_max_it


def read_inputs(problem) -> tuple:
    """The Constants and Functions the problem's forms (and Dirichlet values) read that are neither
    its controls nor its own work Functions, in a fixed order."""
    forms = (problem.F, problem.J) if hasattr(problem, "F") else (problem.a, problem.L)
    own = {id(problem.control(n)) for n in problem.control_names}
    own |= {id(getattr(problem, name)) for name in ("u", "lam", "step") if hasattr(problem, name)}
    found: dict = {}
    candidates = [obj for form in forms for obj in (*form.coefficients(), *form.constants())]
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
        self.size = _CAP_FIELDS + sum(self._sizes)

    def pack(self, system) -> np.ndarray:
        """The state the next solve of ``system`` reads, as one (size,) float64 array."""
        caps = system.caps
        caps = [_NO_CAP if c is None else float(c) for c in (caps.max_it, caps.inner_max_it)]
        return np.concatenate([np.asarray(caps, dtype=np.float64),
                               *(np.asarray(value_of(obj), dtype=np.float64).ravel() for obj in self._inputs)])

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
        current = self.pack(system)
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
        offset = _CAP_FIELDS
        for obj, size in zip(self._inputs, self._sizes):
            values = packed[offset:offset + size]
            offset += size
            if hasattr(obj, "x"):
                obj.x.array[:] = values
            else:
                obj.value = values.reshape(np.shape(obj.value)) if np.ndim(obj.value) else values[0]
