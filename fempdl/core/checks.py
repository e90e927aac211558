"""Argument checks shared across floors; each error names the argument, what it got and what to do."""
from __future__ import annotations

import numpy as np

__all__ = ["check_int", "is_int", "is_real", "python_number"]


def is_int(value) -> bool:
    """Whether ``value`` is an int: a python or numpy integer, never a bool (``True`` is an int to python,
    but no count; ``np.bool_`` is no np.integer)."""
    return isinstance(value, (int, np.integer)) and not isinstance(value, bool)


def is_real(value) -> bool:
    """Whether ``value`` is a real number: a python int or float, or a numpy integer or floating, never a
    bool. Neither NaN nor infinity is excluded: the caller checks the range."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)


def python_number(value):
    """A numpy scalar as the python int or float it holds, anything else unchanged: a value that is
    stored, compared or written as JSON keeps the repr and type a python number gives it."""
    return value.item() if isinstance(value, (np.integer, np.floating)) else value


def check_int(name: str, value, *, minimum: int, maximum: int | None = None, hint: str = "") -> None:
    """Raise TypeError unless ``value`` is an int (numpy ints too, bools not), ValueError outside [minimum, maximum]."""
    if not is_int(value):
        raise TypeError(f"{name} must be an int, got {value!r}" + (f"; {hint}" if hint else ""))
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}" + (f"; {hint}" if hint else ""))
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be <= {maximum} (the largest PETSc int of this build), got {value!r}")
