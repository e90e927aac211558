"""Pieces shared by the PDE modules: spaces, coefficients (Functions or Constants), Dirichlet data."""
from __future__ import annotations

import math
import warnings

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_int, is_real
from fempdl.core.mesh import TaggedMesh

# Spaces a coefficient (kappa) may live in.
COEFFICIENT_SPACES = {"P1": ("Lagrange", 1), "DG0": ("DG", 0)}


# What a form offers in place of a network: a UFL law whose parameters are controls.
NO_NETWORK_IN_FORMS = ("a form is UFL, compiled once to C, and torch cannot run inside its code: wrap the module as a "
                       "coefficient that torch evaluates at the quadrature points, q=lambda u: fempdl.Network(module, "
                       "operands=(u,)), or write the law as a UFL expression of u whose parameters are controls")


def _is_torch(obj) -> bool:
    """A torch module, tensor or function (told by its type's module: the forms do not import torch)."""
    return (getattr(type(obj), "__module__", None) or "").split(".")[0] == "torch"


def _raised_in_torch(exc: BaseException) -> bool:
    tb = exc.__traceback__
    while tb is not None:
        if "/torch/" in tb.tb_frame.f_code.co_filename.replace("\\", "/"):
            return True
        tb = tb.tb_next
    return False


def ufl_law(law, u, name: str):
    """``law(u)``, a user's constitutive function of the UFL unknown, refusing torch code in one line."""
    if _is_torch(law):
        raise TypeError(f"{name} is a torch {type(law).__name__}; {NO_NETWORK_IN_FORMS}")
    try:
        value = law(u)
    except Exception as exc:
        if _raised_in_torch(exc):
            raise TypeError(f"{name}(u) called torch on the UFL unknown ({type(exc).__name__}: {exc}); "
                            f"{NO_NETWORK_IN_FORMS}") from exc
        raise
    if not (isinstance(value, ufl.core.expr.Expr) or is_real(value)):
        raise TypeError(f"{name}(u) must return a UFL expression of u, got a {type(value).__name__}"
                        + (f"; {NO_NETWORK_IN_FORMS}" if _is_torch(value) else ""))
    return value


def check_controls(requested, allowed: tuple, pde: str) -> tuple:
    """The requested control names as a tuple, or a ValueError naming the allowed ones."""
    if isinstance(requested, str):
        requested = (requested,)
    requested = tuple(requested)
    unknown = [c for c in requested if c not in allowed]
    if unknown:
        raise ValueError(f"{pde}: unknown control(s) {unknown}; allowed controls are {list(allowed)}")
    if len(set(requested)) != len(requested):
        raise ValueError(f"{pde}: controls {list(requested)} contain duplicates")
    return requested


def check_degree(degree) -> int:
    if not is_int(degree) or degree < 1:
        raise ValueError(f"degree must be an int >= 1, got {degree!r}")
    return int(degree)


def coefficient_space(msh, kind: str):
    """The space of a scalar coefficient: ``"P1"`` or ``"DG0"``."""
    if kind not in COEFFICIENT_SPACES:
        raise ValueError(f"kappa_space must be one of {list(COEFFICIENT_SPACES)}, got {kind!r}")
    return _dolfinx.function_space(msh, *COEFFICIENT_SPACES[kind])


def make_function(space, value, name: str, *, positive: bool = False) -> dolfinx.fem.Function:
    """A Function on ``space`` holding ``value``: a float or a callable x (3, N) -> (N,).

    ``positive``: the values must be > 0 (a diffusion coefficient: zero or
    negative values make the operator singular or indefinite)."""
    fn = dolfinx.fem.Function(space, name=name)
    if _is_torch(value):
        raise TypeError(f"{name} is a torch {type(value).__name__}; give a float or a callable x (3, N) -> (N,) "
                        f"numpy values, or make {name} a control and pass its values as a layer input")
    if callable(value):
        try:
            fn.interpolate(value)
        except Exception as exc:
            if _raised_in_torch(exc):
                raise TypeError(f"{name}: the callable called torch on numpy coordinates ({type(exc).__name__}: "
                                f"{exc}); return numpy values, or make {name} a control and pass a tensor as a "
                                "layer input") from exc
            raise
    elif is_real(value):
        if not math.isfinite(value):
            raise ValueError(f"{name} must be finite, got {value!r}")
        fn.x.array[:] = float(value)
    else:
        raise TypeError(f"{name} must be a float or a callable x -> values, got {type(value).__name__}")
    if not np.all(np.isfinite(fn.x.array)):
        raise ValueError(f"{name}: the callable returned NaN or inf values")
    if positive:
        _check_positive(name, fn.function_space.mesh.comm.allreduce(float(fn.x.array.min(initial=np.inf)), op=MPI.MIN))
    return fn


def _check_positive(name: str, lowest: float) -> None:
    if lowest <= 0:
        raise ValueError(f"{name} must be > 0 everywhere (a diffusion coefficient: zero or negative values "
                         f"make the operator singular or indefinite), got a minimum of {lowest!r}")


def make_coefficient(space, value, name: str, *, control: bool, positive: bool = False):
    """The coefficient ``name`` of a form: a Function on ``space`` when it is a control or ``value`` is
    a callable (:func:`make_function`), else a ``fem.Constant`` holding the number ``value``.

    A fixed number is no field: as a Function the kernels interpolate it at every quadrature point
    and pack its DOFs at every assembly (a Jacobian of nonlinear heat with kappa and alpha as P1
    Functions takes 1.4x the time of one with Constants); as a Constant it is one value, and the
    same mathematics."""
    if control or callable(value) or not is_real(value):
        return make_function(space, value, name, positive=positive)
    if not math.isfinite(value):
        raise ValueError(f"{name} must be finite, got {value!r}")
    if positive:
        _check_positive(name, float(value))
    return dolfinx.fem.Constant(space.mesh, float(value))


def fixed_constants(fns: dict, names) -> dict:
    """The coefficients among ``names`` that are fixed numbers (``fem.Constant``): registered as the
    problem's Constants, so their documented bounds are checked at every call, as a control's are, however
    a loop changes them (``problem.constants["kappa"].value = ...``)."""
    return {name: fns[name] for name in names if isinstance(fns[name], dolfinx.fem.Constant)}


def positive_constant(msh, value, name: str) -> dolfinx.fem.Constant:
    """A ``fem.Constant`` (so the value can change without recompiling) that must be > 0."""
    if not is_real(value) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return dolfinx.fem.Constant(msh, float(value))


def nonnegative_constant(msh, value, name: str):
    if not is_real(value) or not math.isfinite(value) or value < 0:
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return dolfinx.fem.Constant(msh, float(value))


def dirichlet_bcs(tagged: TaggedMesh, V, g, dirichlet, *, within=None) -> tuple:
    """Dirichlet conditions u = g on the boundary parts named by ``dirichlet``.

    Args:
        dirichlet: ``None`` for the whole boundary; an iterable of facet tag
            names (bundled meshes) or integers; an empty tuple for none.
        within: ``(W, index)`` when ``V`` is subspace ``index`` of the mixed space W, collapsed
            (``g`` lives on V): the condition then constrains that subspace of W.
    """
    if dirichlet is None:
        facets = _dolfinx.boundary_facets(tagged.mesh)
    else:
        parts = (dirichlet,) if isinstance(dirichlet, (str, int, np.integer)) else tuple(dirichlet)
        if not parts:
            return ()
        facets = tagged_facets(tagged, parts)
    value = make_function(V, g, "g")
    if within is not None:
        return (_dolfinx.dirichlet_bc_on_subspace(*within, value, facets),)
    return (_dolfinx.dirichlet_bc(V, value, facets),)


def tagged_facets(tagged: TaggedMesh, parts: tuple, argname: str = "dirichlet") -> np.ndarray:
    """The facets (sorted, unique) of the tag names or integers ``parts``; errors name ``argname``."""
    if tagged.facet_tags is None:
        raise ValueError(f"{argname}={list(parts)} needs facet tags, but this mesh has none; "
                         f"pass {argname}=None or load a tagged .msh file")
    try:
        values = [tagged.facet_tag(p) if isinstance(p, str) else int(p) for p in parts]
    except ValueError as err:
        raise ValueError(f"{argname}={list(parts)}: {err}") from None
    ft = tagged.facet_tags
    # Under MPI a rank may own no facet of a tag: a tag is unknown only if no rank has it.
    present = set().union(*tagged.mesh.comm.allgather(set(np.unique(ft.values).tolist())))
    missing = [v for v in values if v not in present]
    if missing:
        raise ValueError(f"{argname} facet tag(s) {missing} do not occur in the mesh; "
                         f"tags present: {sorted(present)}")
    return np.unique(np.concatenate([ft.find(v) for v in values])).astype(np.int32)


#: The rule of the locking warning: displacement-only P_k warns when lmbda / mu = 2 nu / (1 - 2 nu)
#: exceeds this, i.e. nu > 5/11 (about 0.455). Chosen where P1's L2 error on a small clamped problem
#: (the unit square, 16 x 16, a divergence-free manufactured displacement, valid for every nu) first
#: doubles its nu = 0.3 error; tests/test_elasticity_locking.py re-measures it.
LOCKING_LAME_RATIO = 10.0


def warn_if_locking(form: str, nu: float, degree: int, fix: str) -> None:
    """Warn (UserWarning) when a displacement-only P_k form meets lmbda / mu > :data:`LOCKING_LAME_RATIO`;
    ``fix`` says what to do instead."""
    ratio = 2 * nu / (1 - 2 * nu)
    if ratio > LOCKING_LAME_RATIO:
        warnings.warn(f"{form}: nu={nu:g} gives lmbda/mu={ratio:.3g} > {LOCKING_LAME_RATIO:g}: displacement-only "
                      f"P{degree} locks (displacements far too small as nu -> 0.5); {fix}", UserWarning, stacklevel=3)
