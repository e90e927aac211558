"""fempdl: finite-element PDE solves (DOLFINx + PETSc) as differentiable PyTorch layers.

Public names::

    from fempdl import Problem, forms, mesh
    from fempdl.ksp_adjoint import KSPOptions, CappedSolver, SolveStats
    from fempdl.bridge_torch import SolveLayer
"""
from fempdl import forms, mesh
from fempdl.problem import Problem

__version__ = "0.1.0"
__all__ = ["Problem", "forms", "mesh", "__version__"]
