"""fempdl: finite-element PDE solves (DOLFINx + PETSc) as differentiable PyTorch layers.

Public names::

    from fempdl import Problem, forms, mesh
    from fempdl.ksp_adjoint import KSPOptions, CappedSolver, SolveStats
    from fempdl.bridge_torch import SolveLayer
"""
import logging
import os

# OpenMP threads (torch's, the BLAS's) that spin-wait between parallel regions
# stall any other busy process on the same cores (scripts/bench_stall.py). The policy is read when the OpenMP
# runtime loads, so it is set here, before anything that loads it; a value the
# user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# The version shim first: it loads MPI before DOLFINx, which PyPI's DOLFINx needs.
from fempdl import _dolfinx  # noqa: F401  isort: skip
from fempdl import forms, mesh
from fempdl.problem import Problem

# Library messages (epoch lines, PRDP refinements, K_eps) go to the "fempdl" logger;
# an application shows them with logging.basicConfig(level=logging.INFO).
logging.getLogger("fempdl").addHandler(logging.NullHandler())

__version__ = "0.1.0"
__all__ = ["Problem", "forms", "mesh", "__version__"]
