"""One linearised step of the vector Burgers (advection-diffusion) equation.

    u/dt + (w·∇)u - nu Δu = f + u_prev/dt,

velocity only (no pressure, no incompressibility), vector Lagrange P_k. With
w = u_prev it is the semi-implicit Burgers step. Weak form: find u in V_g such
that for all v in V_0

    ∫ u·v/dt + ((w·∇)u)·v + nu ∇u:∇v dx
      + Σ_K ∫_K tau ((w·∇)v) · (u/dt + (w·∇)u - nu Δu) dx           (SUPG)
    = ∫ (f + u_prev/dt)·v dx + Σ_K ∫_K tau ((w·∇)v) · (f + u_prev/dt) dx,

tau as in :func:`fempdl.forms._flow.supg_tau` (SUPG on by default: Galerkin
oscillates for cell Péclet numbers above 1). u = g on the Dirichlet parts
(``velocity``; default u = 0 on the whole boundary), natural (zero
normal-derivative) elsewhere. The matrix is non-symmetric: use GMRES
(``KSPOptions.preset("gmres")`` or ``"gmres-ilu"``).

Controls: ``"w"`` (matrix; with SUPG also the right-hand side), ``"u_prev"``
and ``"f"`` (right-hand side), all in the solution space V, so a step's output
is the next step's ``u_prev`` and ``w``.
"""
from __future__ import annotations

import ufl

from fempdl.core import _dolfinx
from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import check_controls, check_degree, positive_constant
from fempdl.forms._flow import supg_measure, supg_tau, vector_function, velocity_bcs, warn_if_convection_dominated

CONTROLS = ("w", "u_prev", "f")


def problem(msh, controls=("w", "u_prev"), *, nu: float = 1e-2, dt: float = 0.1, degree: int = 1,
            supg: bool = True, w=0.0, u_prev=0.0, f=0.0, velocity=None) -> Problem:
    """Build one Burgers step on ``msh`` (arguments as in :func:`fempdl.forms.oseen.problem`).

    Returns:
        A :class:`fempdl.Problem`; ``problem.constants`` holds ``nu`` and ``dt``.
    """
    controls = check_controls(controls, CONTROLS, "burgers")
    if not isinstance(supg, bool):
        raise TypeError(f"supg must be True or False, got {supg!r}")
    tagged = as_tagged(msh)
    msh_ = tagged.mesh
    V = _dolfinx.function_space(msh_, "Lagrange", check_degree(degree), shape=(msh_.geometry.dim,))
    nu_c = positive_constant(msh_, nu, "nu")
    dt_c = positive_constant(msh_, dt, "dt")
    bcs, _ = velocity_bcs(tagged, V, None, velocity, V)
    fns = {"w": vector_function(V, w, "w"), "u_prev": vector_function(V, u_prev, "u_prev"),
           "f": vector_function(V, f, "f")}
    w_fn, source = fns["w"], fns["f"] + fns["u_prev"] / dt_c
    warn_if_convection_dominated(tagged.mesh, w_fn, nu, supg)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    a = (ufl.inner(u / dt_c + ufl.dot(ufl.grad(u), w_fn), v) + nu_c * ufl.inner(ufl.grad(u), ufl.grad(v))) * ufl.dx
    L = ufl.inner(source, v) * ufl.dx
    if supg:
        tau = supg_tau(msh_, w_fn, nu_c, dt_c)
        streamline = ufl.dot(ufl.grad(v), w_fn)
        supg_dx = supg_measure(degree)
        residual = u / dt_c + ufl.dot(ufl.grad(u), w_fn) - nu_c * ufl.div(ufl.grad(u))
        a = a + tau * ufl.inner(streamline, residual) * supg_dx
        L = L + tau * ufl.inner(streamline, source) * supg_dx
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls}, constants={"nu": nu_c, "dt": dt_c},
                   positive=("nu", "dt"))
