"""One Oseen step: incompressible flow linearised around an advecting velocity w.

    u/dt + (w·∇)u - nu Δu + ∇p = f + u_prev/dt,   div u = 0,

Taylor-Hood P2-P1 (``degree`` k: vector P_k x P_(k-1)). With w = u_prev this is
the semi-implicit (Oseen-linearised) Navier-Stokes step. Weak form: find (u, p)
in V_g x Q such that for all (v, q) in V_0 x Q

    ∫ u·v/dt + ((w·∇)u)·v + nu ∇u:∇v - p div v - q div u dx
      + ∫ gamma div u div v dx                                     (grad-div)
      + Σ_K ∫_K tau ((w·∇)v) · (u/dt + (w·∇)u - nu Δu + ∇p) dx      (SUPG)
    = ∫ (f + u_prev/dt)·v dx + Σ_K ∫_K tau ((w·∇)v) · (f + u_prev/dt) dx.

Stabilisation (why): Taylor-Hood is inf-sup stable, so no pressure
stabilisation (PSPG) is needed; at small nu the Galerkin convection term
oscillates once the cell Péclet number |w| h / (2 nu) exceeds 1, which SUPG
(``supg=True``, the default; tau from :func:`fempdl.forms._flow.supg_tau`)
damps along streamlines consistently (the residual of the exact solution is
zero). Grad-div (``grad_div=gamma`` >= 0, default 0) adds mass conservation
and helps the Schur-complement preconditioner at small nu.

Boundary conditions and the enclosed-flow pressure null space: as in
:mod:`fempdl.forms.stokes`. Output and :meth:`Problem.split`: as there.

Controls: ``"w"`` (enters the matrix, and with SUPG also the right-hand side,
non-affinely through tau), ``"u_prev"`` and ``"f"`` (affine right-hand-side
terms without SUPG; with SUPG their coefficient depends on w, so they are
affine only while w is not a control). All three live in the velocity space
``problem.field_space("u")``, so ``problem.split(x)["u"]`` feeds the next step.
"""
from __future__ import annotations

import ufl

from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import check_controls, nonnegative_constant, positive_constant
from fempdl.forms._flow import (
    flow_problem,
    supg_measure,
    supg_tau,
    taylor_hood,
    vector_function,
    warn_if_convection_dominated,
)

CONTROLS = ("w", "u_prev", "f")


def problem(msh, controls=("w", "u_prev"), *, nu: float = 1e-2, dt: float = 0.1, degree: int = 2,
            supg: bool = True, grad_div: float = 0.0, w=0.0, u_prev=0.0, f=0.0, velocity=None) -> Problem:
    """Build one Oseen step on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: names among ``("w", "u_prev", "f")``.
        nu: kinematic viscosity (> 0); dt: time step (> 0).
        degree: velocity degree k >= 2.
        supg: streamline-upwind stabilisation of the momentum equation.
        grad_div: grad-div parameter gamma >= 0 (a viscosity).
        w, u_prev, f: fixed values (float, gdim floats, or callable x -> (gdim, N)).
        velocity: Dirichlet velocity data ``{part: value}`` (``None``: no-slip everywhere).

    Returns:
        A :class:`fempdl.Problem` with fields ``"u"``, ``"p"``; ``problem.constants``
        holds ``nu``, ``dt`` and ``grad_div``, and ``problem.enclosed`` says whether the pressure
        constant is projected out.
    """
    controls = check_controls(controls, CONTROLS, "oseen")
    if not isinstance(supg, bool):
        raise TypeError(f"supg must be True or False, got {supg!r}")
    tagged = as_tagged(msh)
    W, V, nu_c, bcs, enclosed = taylor_hood(tagged, degree, nu, velocity)
    dt_c = positive_constant(tagged.mesh, dt, "dt")
    gamma = nonnegative_constant(tagged.mesh, grad_div, "grad_div")
    fns = {"w": vector_function(V, w, "w"), "u_prev": vector_function(V, u_prev, "u_prev"),
           "f": vector_function(V, f, "f")}
    w_fn, source = fns["w"], fns["f"] + fns["u_prev"] / dt_c
    warn_if_convection_dominated(tagged.mesh, w_fn, nu, supg)
    (u, p), (v, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
    a = (ufl.inner(u / dt_c + ufl.dot(ufl.grad(u), w_fn), v) + nu_c * ufl.inner(ufl.grad(u), ufl.grad(v))
         - p * ufl.div(v) - q * ufl.div(u) + gamma * ufl.div(u) * ufl.div(v)) * ufl.dx
    L = ufl.inner(source, v) * ufl.dx
    if supg:
        tau = supg_tau(tagged.mesh, w_fn, nu_c, dt_c)
        streamline = ufl.dot(ufl.grad(v), w_fn)
        supg_dx = supg_measure(degree)
        residual = u / dt_c + ufl.dot(ufl.grad(u), w_fn) - nu_c * ufl.div(ufl.grad(u)) + ufl.grad(p)
        a = a + tau * ufl.inner(streamline, residual) * supg_dx
        L = L + tau * ufl.inner(streamline, source) * supg_dx
    return flow_problem(W, a, L, bcs, enclosed, fns, controls, {"nu": nu_c, "dt": dt_c, "grad_div": gamma})
