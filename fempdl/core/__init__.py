"""Floor 0, the FEniCSx side: the DOLFINx version shim, meshes and their generation, Problem,
XDMF/PNG output, memory and mesh-size budgets, MPI helpers and argument checks. Nothing here
imports torch's layers or PETSc's solvers; everything above builds on it."""

# MPI before DOLFINx and PETSc: PyPI's builds find libmpi only once mpi4py has loaded it.
from mpi4py import MPI  # noqa: E402,F401
