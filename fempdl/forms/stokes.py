"""Steady Stokes flow -nu Δu + ∇p = f, div u = 0, Taylor-Hood P2-P1.

Weak form: find (u, p) in W = V_g x Q (V: vector P_k, Q: P_(k-1), k = ``degree``)
such that for all (v, q) in V_0 x Q

    ∫ nu ∇u : ∇v - p div v - q div u dx = ∫ f · v dx.

Boundary: u = g on the Dirichlet parts (``velocity``: walls, inflow); every
other part is a do-nothing outflow (nu ∂u/∂n - p n = 0). When the Dirichlet
parts cover the whole boundary (an enclosed flow) the pressure is determined
up to a constant: the constant-pressure vector is attached to the operator as
its null space, right-hand sides are projected orthogonal to it, and solutions
are returned orthogonal to it (pressure DOF values of zero sum), forward and
adjoint.

Output: the whole (u, p) vector in W's DOF order; ``problem.split(x)`` gives
``{"u": ..., "p": ...}`` in the collapsed velocity / pressure spaces' orders,
and ``problem.field_space("u")`` the velocity space (the space of ``f``).
Control: ``"f"`` (vector, in the velocity space), affine in the right-hand side.
"""
from __future__ import annotations

import ufl

from fempdl.core.mesh import as_tagged
from fempdl.core.problem import Problem
from fempdl.forms._common import check_controls
from fempdl.forms._flow import flow_problem, taylor_hood, vector_function

CONTROLS = ("f",)


def problem(msh, controls=("f",), *, nu: float = 1.0, degree: int = 2, f=0.0, velocity=None) -> Problem:
    """Build the Stokes problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: ``("f",)`` or ``()``.
        nu: kinematic viscosity (> 0).
        degree: velocity degree k >= 2 (pressure k - 1).
        f: the body force (float, gdim floats, or callable x -> (gdim, N)).
        velocity: ``{boundary part: value}`` Dirichlet velocity data (see
            :func:`fempdl.forms._flow.velocity_bcs`); ``None``: no-slip on the
            whole boundary.

    Returns:
        A :class:`fempdl.Problem` with fields ``"u"``, ``"p"``; ``problem.constants``
        holds ``nu``, and ``problem.enclosed`` says whether the pressure constant is projected out.
    """
    controls = check_controls(controls, CONTROLS, "stokes")
    tagged = as_tagged(msh)
    W, V, nu_c, bcs, enclosed = taylor_hood(tagged, degree, nu, velocity)
    f_fn = vector_function(V, f, "f")
    (u, p), (v, q) = ufl.TrialFunctions(W), ufl.TestFunctions(W)
    a = (nu_c * ufl.inner(ufl.grad(u), ufl.grad(v)) - p * ufl.div(v) - q * ufl.div(u)) * ufl.dx
    L = ufl.inner(f_fn, v) * ufl.dx
    return flow_problem(W, a, L, bcs, enclosed, {"f": f_fn}, controls, {"nu": nu_c})
