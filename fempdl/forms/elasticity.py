"""Linear elasticity (small strain, isotropic): displacement-only, or a locking-free mixed (u, p) form.

Strong form: -div sigma(u) = f in Omega, u = g on Gamma_D (the whole boundary by default),
sigma(u) n = 0 on the rest, with sigma(u) = 2 mu eps(u) + lmbda tr(eps(u)) I, eps(u) = sym grad u,
and the Lamé parameters from Young's modulus E and Poisson's ratio nu:
mu = E / (2 (1 + nu)), lmbda = E nu / ((1 + nu)(1 - 2 nu)), so lmbda / mu = 2 nu / (1 - 2 nu).

``formulation="displacement"`` (the default): find u in V_g = {u in [P_k]^d : u = g on Gamma_D} with

    a(u, v) = ∫ sigma(u) : eps(v) dx  =  ∫ f·v dx = L(v)     for all v in V_0.

It *locks* as nu -> 1/2: the lmbda term forces the discrete div u towards zero, which low-order
displacement spaces can only meet with far too small displacements (P1 loses nearly all of it,
P2 much less but far more than at nu = 0.3). ``problem`` warns when lmbda / mu exceeds
:data:`~fempdl.forms._common.LOCKING_LAME_RATIO` = 10, i.e. nu > 5/11 (where P1's error has doubled; see the constant).

``formulation="mixed"``: the solid pressure p = lmbda div u becomes an unknown (Taylor-Hood:
u in [P_k]^d, p in P_(k-1), k = ``degree`` >= 2); find (u, p) in V_g x Q with

    ∫ 2 mu eps(u) : eps(v) + p div v + q div u - (1 / lmbda) p q dx  =  ∫ f·v dx

for all (v, q) in V_0 x Q (the second equation is div u = p / lmbda; with it the first is the
displacement form). The form is symmetric (indefinite) and stays inf-sup stable as
1 / lmbda = (1 + nu)(1 - 2 nu) / (E nu) -> 0, so nu may be 0.5 itself (incompressible, Stokes-like)
unless the whole boundary is clamped (p would then be determined only up to a constant: refused);
nu = 0 has no pressure (1 / lmbda infinite), so the mixed form takes nu in (0, 0.5]. Solve it
with LU (``"lu"``) or a saddle-point method: CG, Jacobi and AMG assume a positive definite matrix,
and PETSc's Cholesky (no pivoting) fails on the zero pressure block at nu = 0.5.
Output: the whole (u, p) vector in W's DOF order; ``problem.split(x)`` gives ``{"u": ..., "p": ...}``
in the collapsed displacement / pressure spaces' orders, ``problem.field_space("u")`` the
displacement space (the space of ``f``). Dirichlet data constrain the displacement only.

Controls: ``"f"`` (the body force, in the displacement space) and ``"E"`` (Young's modulus, DG0 or
P1: a SIMP-style density enters here); ``f`` enters L affinely, ``E`` the matrix (linearly in the
displacement form; through mu and 1 / lmbda in the mixed one). The displacement form's
``near_nullspace`` holds the rigid-body modes (:func:`fempdl.core.nullspaces.rigid_body_modes`), which
algebraic multigrid needs to converge in few iterations on elasticity; they are modes of the
displacement space alone, so the mixed form has none (``near_nullspace`` is ignored there).
"""
from __future__ import annotations

import numpy as np
import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_int, is_real
from fempdl.core.mesh import as_tagged
from fempdl.core.nullspaces import rigid_body_modes
from fempdl.core.problem import Problem
from fempdl.forms._common import (
    COEFFICIENT_SPACES,
    check_controls,
    check_degree,
    coefficient_space,
    dirichlet_bcs,
    fixed_constants,
    make_coefficient,
    nonnegative_constant,
    tagged_facets,
    warn_if_locking,
)
from fempdl.forms._flow import vector_function

CONTROLS = ("f", "E")
FORMULATIONS = ("displacement", "mixed")


def problem(msh, controls=("f",), *, degree: int | None = None, E=1.0, nu: float = 0.3, E_space: str = "DG0",
            f=0.0, g=0.0, dirichlet=None, near_nullspace: bool = True,
            formulation: str = "displacement") -> Problem:
    """Build the linear elasticity problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh (2D: plane strain; 3D).
        controls: names among ``("f", "E")`` that become layer inputs.
        degree: Lagrange degree k of the displacement: default 1 (``"displacement"``) or
            2 (``"mixed"``, which needs k >= 2: the pressure has degree k - 1).
        E: Young's modulus (> 0; float or callable x -> values), in ``E_space`` (``"DG0"`` or ``"P1"``).
        nu: Poisson's ratio, in [0, 0.5) (``"displacement"``) or (0, 0.5] (``"mixed"``).
        f: the body force (float: every component, gdim floats, or callable x -> (gdim, N)).
        g: the Dirichlet displacement (float: every component, or callable x -> (gdim, N)).
        dirichlet: ``None`` (the whole boundary is clamped) or facet tags (names or ints).
        near_nullspace: hand the rigid-body modes to PETSc (for GAMG); False only to compare.
            Ignored by the mixed formulation (no rigid-body modes of the (u, p) space).
        formulation: ``"displacement"`` (u only; a UserWarning when lmbda / mu >
            :data:`~fempdl.forms._common.LOCKING_LAME_RATIO`, where it locks) or ``"mixed"`` (Taylor-Hood (u, p),
            locking-free; output the whole (u, p) vector, ``problem.split`` splits it).

    Returns:
        A :class:`fempdl.Problem`; ``problem.constants`` holds ``nu`` (``problem.nonnegative``; for
        the mixed form ``problem.positive``). A ``nu`` changed there later is not warned about.
    """
    controls = check_controls(controls, CONTROLS, "elasticity")
    if formulation not in FORMULATIONS:
        raise ValueError(f"formulation must be one of {list(FORMULATIONS)}, got {formulation!r}")
    mixed = formulation == "mixed"
    _check_nu(nu, mixed)
    if E_space not in COEFFICIENT_SPACES:
        raise ValueError(f"E_space must be one of {list(COEFFICIENT_SPACES)}, got {E_space!r}")
    tagged = as_tagged(msh)
    gdim = tagged.mesh.geometry.dim
    if mixed:
        degree = 2 if degree is None else degree
        if not is_int(degree) or degree < 2:
            raise ValueError(f"formulation='mixed' needs degree >= 2 (Taylor-Hood: displacement P_k, pressure "
                             f"P_(k-1)), got {degree!r}")
        W = _dolfinx.taylor_hood_space(tagged.mesh, int(degree))
        V, _ = _dolfinx.collapsed_subspace(W, 0)
    else:
        degree = check_degree(1 if degree is None else degree)
        warn_if_locking("elasticity", nu, degree, 'pass formulation="mixed" (Taylor-Hood u, p: locking-free)')
        W = V = _dolfinx.function_space(tagged.mesh, "Lagrange", degree, shape=(gdim,))
    f_fn = vector_function(V, f, "f")
    E_fn = make_coefficient(coefficient_space(tagged.mesh, E_space), E, "E", control="E" in controls, positive=True)
    nu_c = nonnegative_constant(tagged.mesh, nu, "nu")
    bcs = dirichlet_bcs(tagged, V, g, dirichlet, within=(W, 0) if mixed else None)
    if not bcs:
        raise ValueError("elasticity: dirichlet=() leaves rigid-body motions free; clamp at least one boundary part")
    if mixed and nu == 0.5 and _clamps_whole_boundary(tagged, dirichlet):
        raise ValueError("elasticity: formulation='mixed' with nu=0.5 (incompressible) on a body clamped on its "
                         "whole boundary determines the pressure only up to a constant; take nu < 0.5 (e.g. "
                         "0.49999, well posed and locking-free) or leave part of the boundary traction-free")
    a = (mixed_form if mixed else displacement_form)(W, E_fn, nu_c)
    v = ufl.TestFunctions(W)[0] if mixed else ufl.TestFunction(W)
    L = ufl.inner(f_fn, v) * ufl.dx
    fns = {"f": f_fn, "E": E_fn}
    fixed = fixed_constants(fns, ("E",))
    positive = {"E"} & set(controls) | set(fixed)
    kwargs = ({"fields": {"u": 0, "p": 1}, "positive": positive | {"nu"}} if mixed else
              {"near_nullspace": rigid_body_modes(V) if near_nullspace else (), "positive": positive,
               "nonnegative": ("nu",)})
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls}, constants={"nu": nu_c, **fixed},
                   symmetric=True, **kwargs)


def lame(E, nu):
    """(mu, lmbda) of Young's modulus and Poisson's ratio (UFL expressions or numbers)."""
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def _eps(w):
    return ufl.sym(ufl.grad(w))


def displacement_form(W, E, nu) -> ufl.Form:
    """a(u, v) = ∫ (2 mu eps(u) + lmbda tr(eps(u)) I) : eps(v) dx on the vector space W."""
    mu, lmbda = lame(E, nu)
    u, v = ufl.TrialFunction(W), ufl.TestFunction(W)
    gdim = W.mesh.geometry.dim
    return ufl.inner(2 * mu * _eps(u) + lmbda * ufl.tr(_eps(u)) * ufl.Identity(gdim), _eps(v)) * ufl.dx


def mixed_form(W, E, nu) -> ufl.Form:
    """a((u, p), (v, q)) = ∫ 2 mu eps(u) : eps(v) + p div v + q div u - (1 / lmbda) p q dx on W = V x Q.

    1 / lmbda = (1 + nu)(1 - 2 nu) / (E nu) is written out, so nu = 0.5 gives exactly 0."""
    mu, _ = lame(E, nu)
    inverse_lmbda = (1 + nu) * (1 - 2 * nu) / (E * nu)
    (u, p), (v, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
    return (2 * mu * ufl.inner(_eps(u), _eps(v)) + p * ufl.div(v) + q * ufl.div(u)
            - inverse_lmbda * p * q) * ufl.dx


def _check_nu(nu, mixed: bool) -> None:
    if not is_real(nu):
        raise ValueError(f"nu must be a Poisson's ratio (a real number), got {nu!r}")
    if mixed and not 0.0 < nu <= 0.5:
        raise ValueError(f"nu must be a Poisson's ratio in (0, 0.5] for formulation='mixed' (its pressure term "
                         f"has 1/lmbda, infinite at nu=0), got {nu!r}; at nu=0 use formulation='displacement'")
    if not mixed and not 0.0 <= nu < 0.5:
        raise ValueError(f"nu must be a Poisson's ratio in [0, 0.5), got {nu!r}; formulation='mixed' takes nu "
                         "up to 0.5 (near-incompressible and incompressible solids)")


def _clamps_whole_boundary(tagged, dirichlet) -> bool:
    """Whether the Dirichlet parts cover every boundary facet (on every rank)."""
    if dirichlet is None:
        return True
    parts = (dirichlet,) if isinstance(dirichlet, (str, int, np.integer)) else tuple(dirichlet)
    free = np.setdiff1d(_dolfinx.boundary_facets(tagged.mesh), tagged_facets(tagged, parts))
    return tagged.mesh.comm.allreduce(len(free)) == 0
