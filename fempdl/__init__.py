"""fempdl: finite-element PDE solves (DOLFINx + PETSc) as differentiable PyTorch layers.

Public names, in one line::

    from fempdl import Problem, SolveLayer, KSPOptions, PRDP, SolverFailedError, forms, mesh
    from fempdl import NonlinearProblem, NonlinearSolveLayer, NewtonOptions
    from fempdl import Network, derivative       # a torch network inside a form, and d/du through it

They load on first use, so ``import fempdl`` (and ``fempdl --help``) does not pay
for DOLFINx and torch until a name needs them.

This module is the documented import path. So are its public submodules
``fempdl.forms``, ``fempdl.mesh`` and ``fempdl.io``, and the design card's modules
``fempdl.ksp_adjoint``, ``fempdl.bridge_torch`` and ``fempdl.prdp`` (re-exports of
the same objects; each is an attribute of ``fempdl`` too). The packages below
them are internal, and their module paths may move: ``core`` (FEniCSx),
``solve`` (PETSc), ``iterative`` (torch-only K-step maths), ``layer`` (the torch
layers), ``methods`` (PRDP, SIP, HIG) and ``app`` (scenes and the command).
"""
import importlib
import logging
import os
import signal
import threading

# OpenMP threads (torch's, the BLAS's) that spin-wait between parallel regions
# stall any other busy process on the same cores (benchmarks/bench_stall.py). The policy is read when the OpenMP
# runtime loads, so it is set here, before anything that loads it; a value the
# user set wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

# Library messages (epoch lines, PRDP refinements, K_eps) go to the "fempdl" logger;
# an application shows them with logging.basicConfig(level=logging.INFO).
logging.getLogger("fempdl").addHandler(logging.NullHandler())

__version__ = "0.1.0"


def _python_sigint() -> None:
    """Put Python's SIGINT handler back where the OS default is in place. ``import gmsh`` sets the OS
    default, and a script that imports gmsh before fempdl (as anyone meshing with gmsh does) would then
    be killed by Ctrl-C without unwinding: no KeyboardInterrupt, no ``finally``, no final checkpoint. Only
    the main thread may set a handler; a handler of the user's own (or SIG_IGN) is left alone."""
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT) is signal.SIG_DFL:
        signal.signal(signal.SIGINT, signal.default_int_handler)


_python_sigint()

# Public name -> the module that defines it (imported on first access).
_PUBLIC = {
    "Problem": "fempdl.core.problem",
    "SolveLayer": "fempdl.layer.solve_layer",
    "NonlinearProblem": "fempdl.core.nonlinear_problem",
    "NonlinearSolveLayer": "fempdl.layer.newton_layer",
    "NewtonOptions": "fempdl.solve.newton_options",
    "KSPOptions": "fempdl.solve.options",
    "CappedSolver": "fempdl.solve.capped_solver",
    "SolveStats": "fempdl.solve.stats",
    "CumulativeStats": "fempdl.solve.stats",
    "SolverFailedError": "fempdl.solve.stats",
    "SolverWarning": "fempdl.solve.stats",
    "Caps": "fempdl.solve.caps",
    "PRDP": "fempdl.methods.prdp",
    "PRDPSettings": "fempdl.methods.prdp_settings",
    "k_eps": "fempdl.methods.k_eps",
    "newton_k_eps": "fempdl.methods.k_eps",
    "k_start": "fempdl.methods.k_start",
    "preflight": "fempdl.methods.preflight",
    "reference_physics": "fempdl.layer.reference",
    "NewtonCaps": "fempdl.methods.newton_caps",
    "ConvergedCaps": "fempdl.methods.newton_caps",
    "PointObservation": "fempdl.layer.observation",
    "MassInner": "fempdl.layer.observation",
    "Rollout": "fempdl.layer.rollout",
    "Network": "fempdl.layer.network",
    "derivative": "fempdl.core.pointwise_forms",
}
_SUBMODULES = {"forms": "fempdl.forms", "mesh": "fempdl.mesh", "io": "fempdl.io",
               "ksp_adjoint": "fempdl.ksp_adjoint", "bridge_torch": "fempdl.bridge_torch", "prdp": "fempdl.prdp"}

__all__ = sorted(_PUBLIC) + sorted(_SUBMODULES) + ["__version__"]


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(importlib.import_module(_PUBLIC[name]), name)
    elif name in _SUBMODULES:
        value = importlib.import_module(_SUBMODULES[name])
    else:
        raise AttributeError(f"module 'fempdl' has no attribute {name!r}")
    globals()[name] = value      # later lookups skip this function
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
