"""Argument checks shared across floors; each error names the argument, what it got and what to do."""
from __future__ import annotations

import numpy as np

__all__ = ["check_int"]


def check_int(name: str, value, *, minimum: int, maximum: int | None = None, hint: str = "") -> None:
    """Raise TypeError unless ``value`` is an int (numpy ints too, bools not), ValueError outside [minimum, maximum]."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {value!r}" + (f"; {hint}" if hint else ""))
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}" + (f"; {hint}" if hint else ""))
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be <= {maximum} (the largest PETSc int of this build), got {value!r}")

