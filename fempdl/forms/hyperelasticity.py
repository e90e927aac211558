"""Compressible neo-Hookean hyperelasticity (finite strain, 2D plane strain or 3D), solved by Newton.

A body in its reference configuration Omega (d = 2 or 3) deforms by x = X + u(X), with the
deformation gradient F = I + grad u, C = F^T F, J = det F and the stored energy density

    psi(F) = mu/2 (I_C - d) - mu ln J + lmbda/2 (ln J)^2,      I_C = tr C,

whose first Piola-Kirchhoff stress is P = dpsi/dF = mu (F - F^{-T}) + lmbda ln(J) F^{-T}.
In 2D this is plane strain: the 3D energy with F_33 = 1, since tr C_3D - 3 = tr C_2D - 2.
The Lamé parameters come from Young's modulus E and Poisson's ratio nu as in linear
elasticity (mu = E / (2 (1 + nu)), lmbda = E nu / ((1 + nu)(1 - 2 nu))), so small loads give
:mod:`fempdl.forms.elasticity`'s solution.

Residual (dead loads: the body force B per reference volume, the traction T per reference
area on the loaded part Gamma_T): find u in V_0 = {u in [P_k]^d : u = 0 on Gamma_D} with

    F(u, v) = ∫ P(I + grad u) : grad v dx - ∫ B·v dx - ∫_{Gamma_T} T·v ds = 0   for all v in V_0,

and P N = 0 on the rest of the boundary. The Jacobian is ufl.derivative(F, u).

Boundary parts (what a user of a beam or a box expects): by default the body is clamped
(u = 0) on its end face x = x_min and loaded on its opposite end face x = x_max (the faces of
the bounding box in the first coordinate). ``dirichlet`` and ``traction_on`` take facet tag
names or integers of a tagged mesh, or a marker x (3, N) -> bool array, instead.

Controls: ``"T"`` (the traction, a vector Function on P1 or on the displacement space; only
its values on Gamma_T matter, so its gradient vanishes elsewhere), ``"B"`` (the body force,
in the displacement space) and ``"E"`` (Young's modulus, DG0 or P1: a SIMP-style density
enters here). T and B enter F affinely, E through both Lamé parameters. The problem's
``near_nullspace`` holds the rigid-body modes (:func:`fempdl.core.nullspaces.rigid_body_modes`),
which algebraic multigrid needs for the inner solves of large problems.

Newton: from u = 0 the first step is the linear-elastic solution. On slender bodies under
bending the full step raises ||F|| while it approaches the solution (the axial strain of a
rotated section), so a backtracking line search (``snes_type="newtonls"``), whose merit is
||F||, takes many short steps; plain Newton (the default of
:class:`~fempdl.solve.newton_options.NewtonOptions`) converges in a few while no element inverts.
A full step that inverts an element makes ln J undefined: SNES stops with a NaN residual and the
layer raises. For large loads, load in increments (``initial_guess=`` the previous solution).
"""
from __future__ import annotations

from mpi4py import MPI
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import ufl

from fempdl.core import _dolfinx
from fempdl.core.checks import is_real
from fempdl.core.mesh import TaggedMesh, as_tagged
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.core.nullspaces import rigid_body_modes
from fempdl.forms._common import (
    COEFFICIENT_SPACES,
    check_controls,
    check_degree,
    coefficient_space,
    fixed_constants,
    make_coefficient,
    nonnegative_constant,
    tagged_facets,
    warn_if_locking,
)
from fempdl.forms._flow import vector_function

CONTROLS = ("T", "B", "E")
TRACTION_SPACES = ("P1", "V")
_LOADED = 1          # the tag of the loaded facets in the traction measure's own MeshTags


def problem(msh, controls=("T",), *, degree: int = 1, E=1.0, nu: float = 0.3, E_space: str = "DG0", T=0.0,
            T_space: str = "P1", B=0.0, dirichlet=None, traction_on=None,
            near_nullspace: bool = True) -> NonlinearProblem:
    """Build the neo-Hookean problem on ``msh``.

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or a dolfinx Mesh (2D: plane strain; 3D).
        controls: names among ``("T", "B", "E")`` that become layer inputs.
        degree: Lagrange degree k of the displacement.
        E: Young's modulus (> 0; float or callable x -> values), in ``E_space`` (``"DG0"`` or ``"P1"``).
        nu: Poisson's ratio in [0, 0.5).
        T: the traction on ``traction_on`` (float: every component, gdim floats, or callable
            x -> (gdim, N)), in ``T_space``: ``"P1"`` (vector P1) or ``"V"`` (the displacement space).
        B: the body force (as T), in the displacement space.
        dirichlet: the clamped part: ``None`` (the face x = x_min), facet tags (names or ints),
            or a marker x (3, N) -> bool (N,) of boundary points.
        traction_on: the loaded part, as ``dirichlet``; ``None``: the face x = x_max.
        near_nullspace: hand the rigid-body modes to PETSc (for GAMG); False only to compare.

    Returns:
        A :class:`fempdl.NonlinearProblem` for the displacement u (owned DOF values, gdim
        per node); ``problem.constants`` holds ``nu``.
    """
    controls = check_controls(controls, CONTROLS, "hyperelasticity")
    if not is_real(nu) or not 0.0 <= nu < 0.5:
        raise ValueError(f"nu must be a Poisson's ratio in [0, 0.5) (0.5 is incompressible: lmbda = inf), "
                         f"got {nu!r}")
    if E_space not in COEFFICIENT_SPACES:
        raise ValueError(f"E_space must be one of {list(COEFFICIENT_SPACES)}, got {E_space!r}")
    if T_space not in TRACTION_SPACES:
        raise ValueError(f"T_space must be 'P1' (vector P1) or 'V' (the displacement space), got {T_space!r}")
    tagged = as_tagged(msh)
    degree = check_degree(degree)
    gdim, tdim = tagged.gdim, tagged.tdim
    if gdim not in (2, 3) or tdim != gdim:
        raise ValueError(f"hyperelasticity needs a 2D or 3D body (a mesh whose cells fill the space), got "
                         f"topological dimension {tdim} in {gdim}D")
    V = _dolfinx.function_space(tagged.mesh, "Lagrange", degree, shape=(gdim,))
    clamped = _facets(tagged, dirichlet, "dirichlet", end=0)
    loaded = _facets(tagged, traction_on, "traction_on", end=1)
    comm = tagged.comm
    if comm.allreduce(len(np.setdiff1d(loaded, clamped)), op=MPI.SUM) == 0:
        raise ValueError("traction_on: every loaded facet is also clamped (dirichlet), so the traction would do "
                         "nothing; load a part of the boundary that is free")
    fns = {"T": vector_function(V if T_space == "V" else _dolfinx.function_space(tagged.mesh, "Lagrange", 1,
                                                                                 shape=(gdim,)), T, "T"),
           "B": vector_function(V, B, "B"),
           "E": make_coefficient(coefficient_space(tagged.mesh, E_space), E, "E", control="E" in controls,
                                 positive=True)}
    zero = vector_function(V, 0.0, "clamped")
    bcs = (_dolfinx.dirichlet_bc(V, zero, clamped),)
    warn_if_locking("hyperelasticity", nu, degree, "no mixed form is offered for it: refine the mesh with P2, or "
                    "for small strains use forms.elasticity with formulation=\"mixed\"")
    nu_c = nonnegative_constant(tagged.mesh, nu, "nu")
    E_fn = fns["E"]
    mu = E_fn / (2 * (1 + nu_c))
    lmbda = E_fn * nu_c / ((1 + nu_c) * (1 - 2 * nu_c))

    u = dolfinx.fem.Function(V, name="u")
    v = ufl.TestFunction(V)
    F_def = ufl.Identity(gdim) + ufl.grad(u)
    F_inv_T = ufl.inv(F_def).T
    P = mu * (F_def - F_inv_T) + lmbda * ufl.ln(ufl.det(F_def)) * F_inv_T
    # P is rational in grad u (and has a log), so UFL's degree estimate runs high (it adds
    # degrees for ln and for every division: 8 to 17 for P2); 2k integrates the Jacobian's
    # polynomial part grad v : dP : grad du (degree 2(k - 1) on affine cells) with room to
    # spare, and P1 (grad u constant per cell) exactly.
    dx_stress = ufl.dx(metadata={"quadrature_degree": 2 * degree})
    tags = dolfinx.mesh.meshtags(tagged.mesh, tdim - 1, loaded, np.full(len(loaded), _LOADED, dtype=np.int32))
    ds_loaded = ufl.Measure("ds", domain=tagged.mesh, subdomain_data=tags)(_LOADED)
    F = (ufl.inner(P, ufl.grad(v)) * dx_stress - ufl.inner(fns["B"], v) * ufl.dx
         - ufl.inner(fns["T"], v) * ds_loaded)
    fixed = fixed_constants(fns, ("E",))
    return NonlinearProblem(F, u, bcs, controls={name: fns[name] for name in controls},
                            constants={"nu": nu_c, **fixed}, nonnegative=("nu",),
                            near_nullspace=rigid_body_modes(V) if near_nullspace else (),
                            positive={"E"} & set(controls) | set(fixed))


def _facets(tagged: TaggedMesh, part, argname: str, end: int) -> np.ndarray:
    """Sorted local exterior facets of ``part`` (see :func:`problem`); ``end`` 0/1 picks the
    face x = x_min / x = x_max for ``part=None``. An error if no rank has any."""
    msh = tagged.mesh
    fdim = msh.topology.dim - 1
    if part is None:
        x = msh.geometry.x[:, 0]
        lo = msh.comm.allreduce(float(x.min(initial=np.inf)), op=MPI.MIN)
        hi = msh.comm.allreduce(float(x.max(initial=-np.inf)), op=MPI.MAX)
        target, tol = (lo, hi)[end], 1e-8 * (hi - lo)
        facets = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda p: np.abs(p[0] - target) <= tol)
        what = f"the face x = {target:g} (the default {argname}=None)"
    elif callable(part):
        facets = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda p: np.asarray(part(p), dtype=bool))
        what = f"{argname}'s marker"
    else:
        tag_types = (str, int, np.integer)
        parts = (part,) if isinstance(part, tag_types) else tuple(part) if hasattr(part, "__iter__") else ()
        if not parts or not all(isinstance(p, tag_types) and not isinstance(p, bool) for p in parts):
            raise ValueError(f"{argname} must be None, facet tags (names or ints), or a marker x -> bool; "
                             f"got {part!r}")
        facets = tagged_facets(tagged, parts, argname)
        what = f"{argname}={list(parts)}"
    facets = np.unique(np.asarray(facets, dtype=np.int32))
    if msh.comm.allreduce(len(facets), op=MPI.SUM) == 0:
        raise ValueError(f"{what} selects no boundary facet; name a part of this mesh's boundary")
    return facets
