"""Floor 1, PETSc linear solves on arrays (nothing of torch): solver options and presets, solve
statistics and failures, the KSPs and their PETSc options, and the assembled system of a Problem.
The capped solve and its transposed adjoint: :mod:`fempdl.solve.capped_solver`."""

# MPI before DOLFINx and PETSc: PyPI's builds find libmpi only once mpi4py has loaded it.
from mpi4py import MPI  # noqa: E402,F401
