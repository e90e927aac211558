"""Poisson's equation with a variable coefficient.

Strong form: -div(kappa grad u) = f in Omega, u = g on Gamma_D (the whole
boundary by default), kappa grad u . n = 0 on the rest.

Weak form: find u in V_g = {u in P_k : u = g on Gamma_D} such that

    a(u, v) = ∫ kappa ∇u·∇v dx  =  ∫ f v dx = L(v)     for all v in V_0.

Controls: ``"f"`` (in the solution space V, so solutions can feed sources) and
``"kappa"`` (P1 or DG0). ``f`` enters L affinely, so a layer with only ``f``
as control assembles A once and computes b = M f + b_g per sample by one
sparse product; ``kappa`` enters A, which is then assembled per sample.
"""
from __future__ import annotations

import ufl

from fempdl.core import _dolfinx
from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import (
    check_controls,
    check_degree,
    coefficient_space,
    dirichlet_bcs,
    fixed_constants,
    make_coefficient,
    make_function,
)

CONTROLS = ("f", "kappa")


def problem(msh, controls=("f",), *, degree: int = 1, kappa_space: str = "P1",
            f=1.0, kappa=1.0, g=0.0, dirichlet=None) -> Problem:
    """Build the Poisson problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` (from :func:`fempdl.core.mesh.load`) or a dolfinx Mesh.
        controls: names among ``("f", "kappa")`` that become layer inputs.
        degree: Lagrange degree k of the solution space (and of f).
        kappa_space: ``"P1"`` or ``"DG0"``.
        f, kappa, g: fixed values (float or callable x -> values) of the source,
            the coefficient and the Dirichlet data; controls start at them.
        dirichlet: ``None`` (whole boundary) or facet tags (names or ints).

    Returns:
        A :class:`fempdl.Problem` with the requested controls.
    """
    controls = check_controls(controls, CONTROLS, "poisson")
    tagged = as_tagged(msh)
    degree = check_degree(degree)
    V = _dolfinx.function_space(tagged.mesh, "Lagrange", degree)
    f_fn = make_function(V, f, "f")
    kappa_fn = make_coefficient(coefficient_space(tagged.mesh, kappa_space), kappa, "kappa",
                                control="kappa" in controls, positive=True)
    bcs = dirichlet_bcs(tagged, V, g, dirichlet)
    if not bcs:
        raise ValueError("poisson: dirichlet=() leaves u determined only up to a constant; "
                         "give at least one Dirichlet boundary part")
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    a = kappa_fn * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    L = f_fn * v * ufl.dx
    fns = {"f": f_fn, "kappa": kappa_fn}
    fixed = fixed_constants(fns, ("kappa",))
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls}, symmetric=True, constants=fixed,
                   positive={"kappa"} & set(controls) | set(fixed))
