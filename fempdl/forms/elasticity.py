"""Linear elasticity (small strain, isotropic), with the rigid-body modes as AMG's near null space.

Strong form: -div sigma(u) = f in Omega, u = g on Gamma_D (the whole boundary by default),
sigma(u) n = 0 on the rest, with sigma(u) = 2 mu eps(u) + lmbda tr(eps(u)) I, eps(u) = sym grad u,
and the Lamé parameters from Young's modulus E and Poisson's ratio nu:
mu = E / (2 (1 + nu)), lmbda = E nu / ((1 + nu)(1 - 2 nu)).
Weak form: find u in V_g = {u in [P_k]^d : u = g on Gamma_D} such that

    a(u, v) = ∫ sigma(u) : eps(v) dx  =  ∫ f·v dx = L(v)     for all v in V_0.

Controls: ``"f"`` (the body force, in V) and ``"E"`` (Young's modulus, DG0 or P1: a SIMP-style
density enters here); ``f`` enters L affinely, ``E`` the matrix (linearly). The problem's
``near_nullspace`` holds the rigid-body modes (:func:`fempdl.core.nullspaces.rigid_body_modes`), which
algebraic multigrid needs to converge in few iterations on elasticity.
"""
from __future__ import annotations

import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_real
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
)
from fempdl.forms._flow import vector_function

CONTROLS = ("f", "E")


def problem(msh, controls=("f",), *, degree: int = 1, E=1.0, nu: float = 0.3, E_space: str = "DG0", f=0.0,
            g=0.0, dirichlet=None, near_nullspace: bool = True) -> Problem:
    """Build the linear elasticity problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh (2D: plane strain; 3D).
        controls: names among ``("f", "E")`` that become layer inputs.
        degree: Lagrange degree k of the displacement.
        E: Young's modulus (> 0; float or callable x -> values), in ``E_space`` (``"DG0"`` or ``"P1"``).
        nu: Poisson's ratio in [0, 0.5).
        f: the body force (float: every component, gdim floats, or callable x -> (gdim, N)).
        g: the Dirichlet displacement (float: every component, or callable x -> (gdim, N)).
        dirichlet: ``None`` (the whole boundary is clamped) or facet tags (names or ints).
        near_nullspace: hand the rigid-body modes to PETSc (for GAMG); False only to compare.

    Returns:
        A :class:`fempdl.Problem`; ``problem.constants`` holds ``nu``.
    """
    controls = check_controls(controls, CONTROLS, "elasticity")
    if not is_real(nu) or not 0.0 <= nu < 0.5:
        raise ValueError(f"nu must be a Poisson's ratio in [0, 0.5), got {nu!r}")
    if E_space not in COEFFICIENT_SPACES:
        raise ValueError(f"E_space must be one of {list(COEFFICIENT_SPACES)}, got {E_space!r}")
    tagged = as_tagged(msh)
    degree = check_degree(degree)
    gdim = tagged.mesh.geometry.dim
    V = _dolfinx.function_space(tagged.mesh, "Lagrange", degree, shape=(gdim,))
    f_fn = vector_function(V, f, "f")
    E_fn = make_coefficient(coefficient_space(tagged.mesh, E_space), E, "E", control="E" in controls, positive=True)
    nu_c = nonnegative_constant(tagged.mesh, nu, "nu")
    bcs = dirichlet_bcs(tagged, V, g, dirichlet)
    if not bcs:
        raise ValueError("elasticity: dirichlet=() leaves rigid-body motions free; clamp at least one boundary part")
    mu = E_fn / (2 * (1 + nu_c))
    lmbda = E_fn * nu_c / ((1 + nu_c) * (1 - 2 * nu_c))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)

    def eps(w):
        return ufl.sym(ufl.grad(w))

    def sigma(w):
        return 2 * mu * eps(w) + lmbda * ufl.tr(eps(w)) * ufl.Identity(gdim)

    a = ufl.inner(sigma(u), eps(v)) * ufl.dx
    L = ufl.inner(f_fn, v) * ufl.dx
    fns = {"f": f_fn, "E": E_fn}
    fixed = fixed_constants(fns, ("E",))
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls}, constants={"nu": nu_c, **fixed},
                   nonnegative=("nu",),
                   near_nullspace=rigid_body_modes(V) if near_nullspace else (), symmetric=True,
                   positive={"E"} & set(controls) | set(fixed))
