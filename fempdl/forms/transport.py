"""One implicit step of the advection-diffusion of a scalar marker m by a velocity w.

    m/dt + div(m w) - kappa Δm = f + m_prev/dt,

scalar Lagrange P_k for m, w in a vector Lagrange space (by default P2, the
Taylor-Hood velocity; pass the flow's ``velocity_space`` so a flow step's
output feeds ``w`` without reordering). Weak form, in conservative
(integrated-by-parts) form: find m in V_g such that for all v in V_0

    ∫ m v/dt - m w·∇v + kappa ∇m·∇v dx + ∫_∂Ω m (w·n) v ds
      + Σ_K ∫_K tau (w·∇v) (m/dt + div(m w) - kappa Δm) dx           (SUPG)
    = ∫ (f + m_prev/dt) v dx + Σ_K ∫_K tau (w·∇v) (f + m_prev/dt) dx.

Without SUPG the left-hand side is exactly ∫ (m/dt + div(m w)) v + kappa
∇m·∇v: the conservative form. Testing with v = 1 (no Dirichlet part; the SUPG
term vanishes there since ∇v = 0) gives d/dt ∫ m = ∫ f - ∫_∂Ω m w·n: on an
enclosed domain (w = 0 on the boundary) the marker's mass is conserved to
round-off for any w, divergence-free or not. The boundary term is the free
outflow condition; an inflow part (w·n < 0) needs Dirichlet data
(``dirichlet``, ``g``), or the step is unstable there.

Stabilisation (why): Galerkin oscillates once the cell Péclet number
|w| h / (2 kappa) exceeds 1; SUPG (``supg=True``, the default; tau from
:func:`fempdl.forms._flow.supg_tau` with kappa for nu) adds streamline
diffusion consistently. Without it a warning is raised at construction when
the given w makes the cell Péclet number exceed 1, as in the flow forms.

Controls: ``"w"`` (the matrix; without SUPG affinely, listed in
``problem.affine_matrix_controls``; with SUPG also the right-hand side, through
tau and the streamline test function), ``"m_prev"`` and ``"f"`` (right-hand
side, in the solution space, so a step's output is the next step's
``m_prev``; affine unless SUPG makes their coefficient depend on a w control).
The matrix is non-symmetric: use LU, GMRES or ``"gmres-ilu"``.
"""
from __future__ import annotations

import ufl

from fempdl.core import _dolfinx
from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import (
    check_controls,
    check_degree,
    dirichlet_bcs,
    make_function,
    nonnegative_constant,
    positive_constant,
)
from fempdl.forms._flow import supg_tau, vector_function, warn_if_convection_dominated

CONTROLS = ("w", "m_prev", "f")


def problem(msh, controls=("w", "m_prev"), *, kappa: float = 1e-3, dt: float = 0.1, degree: int = 1,
            velocity_degree: int = 2, velocity_space=None, supg: bool = True, w=0.0, m_prev=0.0, f=0.0,
            g=0.0, dirichlet=()) -> Problem:
    """Build one marker transport step on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: names among ``("w", "m_prev", "f")``.
        kappa: diffusivity (>= 0; 0 is pure advection, SUPG then needed).
        dt: time step (> 0).
        degree: Lagrange degree of the marker.
        velocity_degree: degree of the vector Lagrange space of ``w`` (when
            ``velocity_space`` is not given).
        velocity_space: the vector space ``w`` lives on, e.g. an Oseen
            problem's ``field_space("u")``; must be on ``msh``.
        supg: streamline-upwind stabilisation.
        w, m_prev, f: fixed values (w: float, gdim floats or callable x -> (gdim, N);
            m_prev, f: float or callable x -> (N,)).
        g, dirichlet: Dirichlet data m = g on the facet parts ``dirichlet``
            (``()``: none, the default, for an enclosed domain; ``None``: the
            whole boundary).

    Returns:
        A :class:`fempdl.Problem`; ``problem.constants`` holds ``kappa`` and ``dt``.
    """
    controls = check_controls(controls, CONTROLS, "transport")
    if not isinstance(supg, bool):
        raise TypeError(f"supg must be True or False, got {supg!r}")
    tagged = as_tagged(msh)
    msh_ = tagged.mesh
    V = _dolfinx.function_space(msh_, "Lagrange", check_degree(degree))
    if velocity_space is None:
        velocity_space = _dolfinx.function_space(msh_, "Lagrange", check_degree(velocity_degree),
                                                 shape=(msh_.geometry.dim,))
    elif velocity_space.mesh is not msh_ or velocity_space.dofmap.index_map_bs != msh_.geometry.dim:
        raise ValueError("velocity_space must be a vector space with gdim components on the same mesh object "
                         "as msh, e.g. an Oseen problem's field_space('u')")
    kappa_c = nonnegative_constant(msh_, kappa, "kappa")
    dt_c = positive_constant(msh_, dt, "dt")
    bcs = dirichlet_bcs(tagged, V, g, dirichlet)
    fns = {"w": vector_function(velocity_space, w, "w"),
           "m_prev": make_function(V, m_prev, "m_prev"),
           "f": make_function(V, f, "f")}
    w_fn, source = fns["w"], fns["f"] + fns["m_prev"] / dt_c
    if kappa == 0 and not supg:
        raise ValueError("kappa=0 without SUPG is pure Galerkin advection (unstable at every cell Péclet number); "
                         "pass supg=True or a diffusivity kappa > 0")
    if kappa > 0:
        warn_if_convection_dominated(msh_, w_fn, kappa, supg)
    m, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    n = ufl.FacetNormal(msh_)
    a = (m * v / dt_c - m * ufl.dot(w_fn, ufl.grad(v)) + kappa_c * ufl.inner(ufl.grad(m), ufl.grad(v))) * ufl.dx \
        + m * ufl.dot(w_fn, n) * v * ufl.ds
    L = source * v * ufl.dx
    if supg:
        tau = supg_tau(msh_, w_fn, kappa_c, dt_c)
        streamline = ufl.dot(w_fn, ufl.grad(v))
        w_degree = _dolfinx.element_degree(velocity_space)
        supg_dx = ufl.dx(metadata={"quadrature_degree": max(2 * w_degree + 2 * degree - 2, w_degree + 2 * degree - 1)})
        residual = m / dt_c + ufl.div(m * w_fn) - kappa_c * ufl.div(ufl.grad(m))
        a = a + tau * streamline * residual * supg_dx
        L = L + tau * streamline * source * supg_dx
    return Problem(a, L, bcs, controls={name: fns[name] for name in controls},
                   constants={"kappa": kappa_c, "dt": dt_c}, positive=("dt",), nonnegative=("kappa",))
