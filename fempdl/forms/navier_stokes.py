"""Steady incompressible Navier-Stokes flow, Taylor-Hood P2-P1, solved by Newton.

Strong form: -div(nu grad u) + (u·∇)u + ∇p = f, div u = 0 in Omega, u = g on the Dirichlet
parts. Residual (signs as in :mod:`fempdl.forms.stokes`, whose operator is the first, third and
fourth terms): find (u, p) in W = V_g x Q (V: vector P_k, Q: P_(k-1), k = ``degree``) with

    F((u, p), (v, q)) = ∫ nu ∇u : ∇v + ((u·∇)u)·v - p div v - q div u - f·v dx = 0

for all (v, q) in V_0 x Q. The Jacobian is ufl.derivative(F, (u, p)) (the convection term
linearised in both of its u's), so Newton converges quadratically near a solution. From the
zero initial guess the first step is the Stokes solution with the same data (the convection
term and its derivative vanish at u = 0); Newton (plain, the default of
:class:`~fempdl.solve.newton_options.NewtonOptions`, or with a backtracking line search,
``snes_type="newtonls"``) carries it from there up to moderate Reynolds numbers (a lid-driven
cavity at Re ~ 100); beyond them start from a solution at a lower Re.

No stabilisation: Taylor-Hood is inf-sup stable, and the Galerkin convection term stays free of
oscillations while the cell Reynolds number |u| h / (2 nu) is about 1 or below (refine the mesh
for smaller nu; :mod:`fempdl.forms.oseen` has SUPG for the time-stepping case).

Boundary: ``velocity`` as in :mod:`fempdl.forms.stokes` (``{part: value}``; parts not named are
do-nothing outflows nu ∂u/∂n - p n = 0). When the Dirichlet parts close the domain the pressure
is determined up to a constant: the constant-pressure vector is the Jacobian's null space,
projected out of every Newton step, so the pressure of the returned state has a zero DOF sum
when Newton starts from one (the zero guess does).

Output: the whole (u, p) vector in W's DOF order; ``problem.split(x)`` gives ``{"u": ..., "p": ...}``
(fields u = 0, p = 1). Controls: ``"f"`` (the body force, in the velocity space, affine in F) and
``"nu"`` (the viscosity as a positive field in ``nu_space``, DG0 or P1; without it nu is a
constant, ``problem.constants["nu"]``).
"""
from __future__ import annotations

import dolfinx.fem
import ufl

from fempdl.core import _dolfinx
from fempdl.core.mesh import as_tagged
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.forms._common import COEFFICIENT_SPACES, check_controls, coefficient_space, make_function
from fempdl.forms._flow import pressure_nullspace, taylor_hood, vector_function

CONTROLS = ("f", "nu")


def problem(msh, controls=("f",), *, nu: float = 1e-2, nu_space: str = "DG0", degree: int = 2, f=0.0,
            velocity=None) -> NonlinearProblem:
    """Build the steady Navier-Stokes problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh.
        controls: names among ``("f", "nu")`` that become layer inputs.
        nu: kinematic viscosity (> 0): the constant, or the initial value of the control ``"nu"``.
        nu_space: the space of the control ``"nu"``: ``"DG0"`` or ``"P1"``.
        degree: velocity degree k >= 2 (pressure k - 1).
        f: the body force (float, gdim floats, or callable x -> (gdim, N)).
        velocity: ``{boundary part: value}`` Dirichlet velocity data (see
            :func:`fempdl.forms._flow.velocity_bcs`); ``None``: no-slip on the whole boundary.

    Returns:
        A :class:`fempdl.NonlinearProblem` with fields ``"u"``, ``"p"``; ``problem.enclosed`` says
        whether the pressure constant is projected out.
    """
    controls = check_controls(controls, CONTROLS, "navier_stokes")
    if nu_space not in COEFFICIENT_SPACES:
        raise ValueError(f"nu_space must be one of {list(COEFFICIENT_SPACES)}, got {nu_space!r}")
    tagged = as_tagged(msh)
    W, V, nu_c, bcs, enclosed = taylor_hood(tagged, degree, nu, velocity)      # validates degree, nu, velocity
    fns = {"f": vector_function(V, f, "f")}
    constants = {}
    if "nu" in controls:
        fns["nu"] = make_function(coefficient_space(tagged.mesh, nu_space), nu, "nu", positive=True)
    else:
        constants["nu"] = nu_c
    viscosity = fns.get("nu", nu_c)

    w = dolfinx.fem.Function(W, name="up")
    u, p = ufl.split(w)
    v, q = ufl.TestFunctions(W)
    F = (viscosity * ufl.inner(ufl.grad(u), ufl.grad(v)) + ufl.inner(ufl.dot(ufl.grad(u), u), v)
         - p * ufl.div(v) - q * ufl.div(u) - ufl.inner(fns["f"], v)) * ufl.dx
    nullspace = ()
    if enclosed:
        _, p_dofs = _dolfinx.collapsed_subspace(W, 1)
        nullspace = pressure_nullspace(p_dofs, W.dofmap.index_map.size_local * W.dofmap.index_map_bs)
    return NonlinearProblem(F, w, bcs, controls={name: fns[name] for name in controls}, fields={"u": 0, "p": 1},
                            nullspace=nullspace, constants=constants, positive={"nu"})
