"""``from fempdl.ksp_adjoint import KSPOptions, CappedSolver, SolveStats``, the import path of the public API;
the capped solver lives in :mod:`fempdl.solve.capped_solver`, its options in :mod:`fempdl.solve.options` and its
statistics and failure types in :mod:`fempdl.solve.stats`."""
from fempdl.solve.capped_solver import CappedSolver
from fempdl.solve.options import PRESETS, KSPOptions
from fempdl.solve.stats import CumulativeStats, SolverFailedError, SolverWarning, SolveStats

__all__ = ["CappedSolver", "KSPOptions", "PRESETS", "SolveStats", "CumulativeStats", "SolverFailedError",
           "SolverWarning"]
