"""Checks of the values a :class:`~fempdl.solve.options.KSPOptions` is built from: PETSc type names,
the ``petsc_options`` mapping (no leading ``-``, no key that fights a field or the semantics), option
values given as strings, and whether a preconditioner factorises (what ``preonly`` needs)."""
from __future__ import annotations

import types
from collections.abc import Mapping
from typing import Any

import numpy as np

__all__ = ["RESERVED_OPTIONS", "OPTION_TYPES", "FORBIDDEN_OPTIONS", "FACTORISING_PC_TYPES", "frozen_petsc_options",
           "factorises", "inner_pc", "parse_option", "check_choice"]

# Preconditioners that solve the system exactly (a factorisation): only with one of
# them is a single application (KSPPREONLY) a direct solve.
FACTORISING_PC_TYPES = frozenset({"lu", "cholesky", "qr", "svd"})
# Keys that have a first-class field; setting them through petsc_options would
# silently fight the cap that PRDP moves.
RESERVED_OPTIONS = {
    "ksp_type": "ksp_type",
    "pc_type": "pc_type",
    "ksp_max_it": "max_it",
    "ksp_rtol": "rtol",
    "ksp_atol": "atol",
    "ksp_divtol": "divtol",
    "ksp_gmres_restart": "gmres_restart",
}
# Types of the fields a reserved key sets (KSPOptions.from_petsc_options); others are str.
OPTION_TYPES = {"max_it": int, "rtol": float, "atol": float, "divtol": float, "gmres_restart": int}
# Prefixes of solvers without options_prefix (their options are all their own).
# Keys that would break the documented semantics outright.
FORBIDDEN_OPTIONS = {
    "ksp_initial_guess_nonzero": "capped solves always start from a zero initial guess",
}


def frozen_petsc_options(options) -> Mapping[str, Any]:
    """The checked ``petsc_options``, keys in lower case: PETSc reads option names case-insensitively,
    so ``KSP_MAX_IT`` would set the cap as ``ksp_max_it`` does, and only the lower-case name can be checked."""
    if not isinstance(options, Mapping):
        raise TypeError(f"petsc_options must be a mapping of option name to value, got {type(options).__name__}")
    clean, given = {}, {}
    for given_key, value in options.items():
        if not isinstance(given_key, str) or not given_key or given_key.startswith("-"):
            raise ValueError(f"petsc_options keys are option names without the leading '-', got {given_key!r}")
        key = given_key.lower()
        if key in given:
            raise ValueError(f"petsc_options[{given[key]!r}] and petsc_options[{given_key!r}] name the same PETSc "
                             "option (PETSc ignores the letter case of option names); give it once")
        given[key] = given_key
        if key in FORBIDDEN_OPTIONS:
            raise ValueError(f"petsc_options[{given_key!r}] is not supported: {FORBIDDEN_OPTIONS[key]}")
        if key in RESERVED_OPTIONS:
            raise ValueError(f"petsc_options[{given_key!r}] conflicts with a KSPOptions field; "
                             f"set {RESERVED_OPTIONS[key]} instead, or build the options from a DOLFINx-style "
                             "dict with KSPOptions.from_petsc_options")
        if value is not None and not isinstance(value, (str, bool, int, float, np.integer, np.floating)):
            raise TypeError(f"petsc_options[{given_key!r}] must be str, number, bool or None, got {value!r}")
        clean[key] = value
    return types.MappingProxyType(clean)


def factorises(pc_type: str, petsc_options: Mapping[str, Any]) -> bool:
    """Whether one application of ``pc_type`` solves the system: a factorisation, or PCREDUNDANT
    whose inner solver (``redundant_ksp_type``, ``redundant_pc_type``; PETSc's defaults preonly + LU)
    is one."""
    if pc_type == "redundant":
        return (petsc_options.get("redundant_ksp_type", "preonly") == "preonly"
                and petsc_options.get("redundant_pc_type", "lu") in FACTORISING_PC_TYPES)
    return pc_type in FACTORISING_PC_TYPES


def inner_pc(petsc_options: Mapping[str, Any]) -> str:
    inner = {k: v for k, v in petsc_options.items() if k in ("redundant_ksp_type", "redundant_pc_type")}
    return f" ({', '.join(f'{k}={v!r}' for k, v in inner.items())})" if inner else ""


def parse_option(key: str, value, kind: type):
    """A reserved option's value as its field's type (strings parsed, as from a command line)."""
    if kind is str:
        if not isinstance(value, str):
            raise TypeError(f"options[{key!r}] must be a type name (str), got {value!r}")
        return value
    if isinstance(value, bool) or value is None:
        raise TypeError(f"options[{key!r}] must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"options[{key!r}] must be a number, got {value!r}") from None
    if kind is int:
        if not number.is_integer():
            raise ValueError(f"options[{key!r}] must be a whole number, got {value!r}")
        return int(number)
    return number


def check_choice(name: str, value, allowed: frozenset) -> None:
    if not isinstance(value, str):
        raise TypeError(f"{name} must be a str, got {value!r}")
    if value not in allowed:
        raise ValueError(f"{name}={value!r} is not a PETSc type; choose one of {sorted(allowed)}")
