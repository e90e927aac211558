"""The Newton forms hyperelasticity and navier_stokes through NonlinearSolveLayer: the forward against
DOLFINx's own Newton, quadratic convergence, the small-load / small-Re limits (linear elasticity,
Stokes), gradients (gradcheck of the converged and the unrolled capped map, central differences),
failures that name SNES's reason, and clear errors for bad input.

Serial: the reference solves and the dense error bounds use this rank's (all) DOFs.
"""
from __future__ import annotations

import warnings

from mpi4py import MPI
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.mesh
import dolfinx.nls.petsc
import numpy as np
import pytest
import torch
import ufl
from petsc4py import PETSc

from fempdl import NewtonOptions, NonlinearSolveLayer, SolveLayer, SolverFailedError, forms
from fempdl.core.mesh import TaggedMesh
from fempdl.solve.newton_stats import SNES_REASON_NAMES
from fempdl.solve.petsc import petsc_to_scipy

pytestmark = pytest.mark.skipif(MPI.COMM_WORLD.size > 1, reason="serial: dense reference algebra")

BEAM_LOAD = 0.01        # traction on the beam's free end: tip deflection ~0.3 of its length (finite rotation)
CAVITY_NU = 0.01        # lid speed 1, side 1: Re = 100
# Newton's tolerance in these tests: far below the claims checked (1e-10), still above the round-off
# floor of ||F|| (about 1e-16 ||F_0|| here), which quadratic convergence jumps to in its last step.
TIGHT = 1e-12


# ------------------------------------------------------------------ meshes and problems
def tagged(msh, parts: dict) -> TaggedMesh:
    """``msh`` with facet tags 1, 2, ... for the boundary parts ``{name: marker}`` in order;
    the last marker may be None for every exterior facet not tagged yet."""
    fdim = msh.topology.dim - 1
    msh.topology.create_connectivity(fdim, msh.topology.dim)
    boundary = dolfinx.mesh.exterior_facet_indices(msh.topology)
    indices, values, taken = [], [], np.empty(0, dtype=np.int32)
    for tag, marker in enumerate(parts.values(), start=1):
        facets = (np.setdiff1d(boundary, taken) if marker is None
                  else dolfinx.mesh.locate_entities_boundary(msh, fdim, marker))
        indices.append(facets)
        values.append(np.full(len(facets), tag, dtype=np.int32))
        taken = np.union1d(taken, facets)
    order = np.argsort(np.concatenate(indices))
    ft = dolfinx.mesh.meshtags(msh, fdim, np.concatenate(indices)[order].astype(np.int32),
                               np.concatenate(values)[order])
    return TaggedMesh(msh, None, ft, "test", {name: tag for tag, name in enumerate(parts, start=1)})


@pytest.fixture(scope="module")
def beam():
    """A 1 x 0.25 cantilever, 8 x 2 cells (27 nodes, 54 P1 DOFs), faces tagged left / right / rest."""
    msh = dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [np.array([0.0, 0.0]), np.array([1.0, 0.25])], [8, 2])
    return tagged(msh, {"left": lambda x: np.isclose(x[0], 0.0), "right": lambda x: np.isclose(x[0], 1.0),
                        "rest": None})


@pytest.fixture(scope="module")
def box():
    """A bare 1 x 0.25 x 0.25 bar, 4 x 1 x 1 cells (60 P1 DOFs): the default parts (end faces x = 0, 1)."""
    return dolfinx.mesh.create_box(MPI.COMM_WORLD, [np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.25, 0.25])],
                                   [4, 1, 1])


@pytest.fixture(scope="module")
def cavity():
    """The unit square, 8 x 8 cells (659 Taylor-Hood DOFs), facets tagged lid (y = 1) / walls."""
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8)
    return tagged(msh, {"lid": lambda x: np.isclose(x[1], 1.0), "walls": None})


def downward(load: float, gdim: int):
    """x -> (gdim, N): the constant vector (0, ..., -load)."""
    return lambda x: np.vstack([np.zeros_like(x[0])] * (gdim - 1) + [np.full_like(x[0], -load)])


def hyper(msh, controls=("T",), **kw):
    parts = {"dirichlet": "left", "traction_on": "right"} if isinstance(msh, TaggedMesh) else {}
    return forms.hyperelasticity.problem(msh, controls=controls, **{**parts, **kw})


def lid_flow(cavity, speed: float = 1.0, **kw):
    # walls after the lid: the two top corners take the wall's zero (the later condition wins)
    return forms.navier_stokes.problem(cavity, velocity={"lid": (speed, 0.0), "walls": 0.0}, **kw)


def smooth_force(x):
    return np.vstack([np.sin(np.pi * x[1]), 0.5 * np.cos(np.pi * x[0])])


# ------------------------------------------------------------------ reference and error bounds
def dolfinx_newton(prob) -> np.ndarray:
    """DOLFINx's own Newton (``NewtonSolver``, full steps, LU) on ``prob``'s residual from zero; no fempdl
    solver code runs. 0.5.2 calls its problem ``fem.petsc.NonlinearProblem``; 0.10+ renamed it
    ``NewtonSolverNonlinearProblem`` (and made ``NonlinearProblem`` the SNES interface)."""
    Problem = getattr(dolfinx.fem.petsc, "NewtonSolverNonlinearProblem", None) or dolfinx.fem.petsc.NonlinearProblem
    prob.u.x.array[:] = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)        # 0.10+: deprecated for SNES, still DOLFINx's
        solver = dolfinx.nls.petsc.NewtonSolver(MPI.COMM_WORLD, Problem(prob.F, prob.u, bcs=list(prob.bcs)))
    solver.convergence_criterion = "residual"
    solver.rtol, solver.atol, solver.max_it = TIGHT, 1e-14, 50
    ksp = solver.krylov_solver
    ksp.setOptionsPrefix("test_reference_newton_")
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    db = PETSc.Options()
    nullspace = None
    if prob.enclosed:
        # The Jacobian of an enclosed flow is singular (the pressure constant): give DOLFINx's
        # solver the same null space and MUMPS's null-pivot detection.
        vec = solver.A.createVecRight()
        vec.setArray(prob.nullspace[0])
        nullspace = PETSc.NullSpace().create(vectors=[vec], comm=MPI.COMM_WORLD)
        solver.A.setNullSpace(nullspace)
        db["test_reference_newton_mat_mumps_icntl_24"] = 1
    ksp.setFromOptions()
    try:
        steps, converged = solver.solve(prob.u)
    finally:
        db.delValue("test_reference_newton_mat_mumps_icntl_24")
    assert converged and steps > 1
    return prob.u.x.array[:prob.output_size].copy()


def newton_error_bound(prob, values: np.ndarray) -> float:
    """||F(u)|| / sigma_min(J(u)) (2-norms, sigma_min on the complement of the null space): to first
    order the distance of ``values`` from the exact discrete solution near it. ``prob`` holds its data
    as fixed values (no controls)."""
    prob.u.x.array[:prob.output_size] = values
    prob.u.x.scatter_forward()
    b = dolfinx.fem.petsc.assemble_vector(prob.F_form)
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    residual = b.getArray().copy()
    residual[prob.bc_dofs] = 0.0                                  # u = g holds exactly there
    A = dolfinx.fem.petsc.assemble_matrix(prob.J_form, bcs=list(prob.bcs))
    A.assemble()
    singular_values = np.linalg.svd(petsc_to_scipy(A).toarray(), compute_uv=False)
    b.destroy()
    A.destroy()
    return float(np.linalg.norm(residual) / singular_values[-1 - len(prob.nullspace)])


def asymptotic_ratios(norms) -> list:
    """rho_{k+1} / rho_k^2 for rho_k = ||F_k|| / ||F_0||, over the steps where Newton is in its
    asymptotic range (rho_k < 0.1) and the new residual is above round-off (rho_{k+1} > 1e-11)."""
    rho = np.asarray(norms) / norms[0]
    return [rho[k + 1] / rho[k] ** 2 for k in range(len(rho) - 1) if rho[k] < 0.1 and rho[k + 1] > 1e-11]


def relative_max(a, b) -> float:
    return float(np.max(np.abs(a - b)) / np.max(np.abs(b)))


# ------------------------------------------------------------------ hyperelasticity: forward
@pytest.mark.parametrize("body", ["beam", "box"])
def test_hyperelastic_forward_equals_dolfinx_newton(body, request):
    msh = request.getfixturevalue(body)
    gdim = (msh.mesh if isinstance(msh, TaggedMesh) else msh).geometry.dim
    load = downward(BEAM_LOAD, gdim)
    prob = hyper(msh)
    layer = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT, snes_type="newtonls"))   # backtracking
    u = layer(T=torch.as_tensor(prob.interpolate(load, "T"))).numpy()
    assert layer.stats.last_newton.reason_name.startswith("CONVERGED")
    reference = hyper(msh, controls=(), T=load)
    u_ref = dolfinx_newton(reference)
    # A genuinely nonlinear state: the end moves a good part of the length (finite rotation).
    assert 0.05 < np.abs(u_ref).max() < 1.0
    # Each solution is within ||F|| / sigma_min(J) of the exact discrete one (first order); those
    # bounds put 1e-10 within reach of what both solves guarantee, not of one run's luck.
    scale = np.abs(u_ref).max()
    bounds = newton_error_bound(reference, u), newton_error_bound(reference, u_ref)
    assert max(bounds) < 1e-11 * scale, bounds
    assert relative_max(u, u_ref) < 1e-10


def test_hyperelastic_newton_converges_quadratically(beam):
    prob = hyper(beam)
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", rtol=TIGHT))
    layer(T=torch.as_tensor(prob.interpolate(downward(BEAM_LOAD, 2), "T")))
    stats = layer.stats.last_newton
    ratios = asymptotic_ratios(stats.residual_norms)
    # Two steps in the asymptotic range at least, each squaring the relative residual (up to a
    # constant); a linearly convergent iteration (a wrong Jacobian) gives rho_k+1 / rho_k^2 ~ c / rho_k.
    assert len(ratios) >= 2 and max(ratios) < 10.0, stats.residual_norms
    assert stats.residual_norms[-1] <= TIGHT * stats.residual_norms[0]


def test_hyperelastic_small_load_limit_is_linear_elasticity(beam):
    """u(s) = s u_lin + O(s^2): the Lamé parameters and plane strain match forms.elasticity."""
    prob = hyper(beam, controls=("B",), E=2.0, nu=0.35)
    linear = forms.elasticity.problem(beam, controls=("f",), E=2.0, nu=0.35, dirichlet="left")
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", rtol=TIGHT))
    direction = torch.as_tensor(prob.interpolate(downward(1.0, 2), "B"))
    u_lin = SolveLayer(linear)(f=direction)
    gaps = []
    for s in (2e-3, 1e-3):
        u = layer(B=s * direction)
        gaps.append(float(torch.linalg.norm(u - s * u_lin) / torch.linalg.norm(s * u_lin)))
    assert gaps[0] < 0.05                       # small deflection: close to linear
    assert 1.8 < gaps[0] / gaps[1] < 2.2        # and the gap is first order in the load


def test_hyperelastic_stress_is_the_stated_energys_derivative(box):
    """The residual's P is dpsi/dF of the docstring's psi = mu/2 (I_C - d) - mu ln J + lmbda/2 (ln J)^2,
    checked against UFL's own derivative of psi at a sheared, stretched state (3D, E and nu not 1)."""
    E, nu = 3.0, 0.3
    prob = hyper(box, controls=(), E=E, nu=nu)                 # no loads: F(u, v) = ∫ P : grad v dx
    prob.u.interpolate(lambda x: np.vstack([0.2 * x[1] + 0.1 * x[0] ** 2, 0.1 * x[2] * x[0], -0.15 * x[2]]))
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    F_def = ufl.variable(ufl.Identity(3) + ufl.grad(prob.u))
    J = ufl.det(F_def)
    psi = mu / 2 * (ufl.tr(F_def.T * F_def) - 3) - mu * ufl.ln(J) + lmbda / 2 * ufl.ln(J) ** 2
    stated = ufl.inner(ufl.diff(psi, F_def), ufl.grad(ufl.TestFunction(prob.V))) * ufl.dx(
        metadata={"quadrature_degree": 2})
    ours, theirs = (dolfinx.fem.petsc.assemble_vector(form).getArray().copy()
                    for form in (prob.F_form, dolfinx.fem.form(stated)))
    assert np.abs(theirs).max() > 1e-3              # a real stress state, not zero against zero
    # The same quantity by two formulas: round-off only, a few ulps of the largest term.
    assert np.abs(ours - theirs).max() < 1e-13 * np.abs(theirs).max()


def test_hyperelastic_traction_on_the_displacement_space(beam):
    """T_space="V" puts T on the (here P2) displacement space: a constant traction is the same function
    there as in P1, so both give the same P2 solution (round-off apart)."""
    on_p1, on_v = hyper(beam, degree=2), hyper(beam, degree=2, T_space="V")
    assert on_p1.control_size("T") == 54 and on_v.control_size("T") == on_v.output_size == 170
    options = NewtonOptions(snes_type="newton", rtol=TIGHT)
    load = downward(BEAM_LOAD, 2)
    u_p1 = NonlinearSolveLayer(on_p1, options)(T=torch.as_tensor(on_p1.interpolate(load, "T")))
    u_v = NonlinearSolveLayer(on_v, options)(T=torch.as_tensor(on_v.interpolate(load, "T")))
    assert 0.05 < float(u_v.abs().max()) < 1.0
    assert relative_max(u_p1.numpy(), u_v.numpy()) < 1e-10


# ------------------------------------------------------------------ hyperelasticity: gradients
def test_hyperelastic_implicit_gradcheck(beam):
    """The converged map T, E -> u: float64 gradcheck of the implicit adjoint (E enters the Jacobian)."""
    prob = hyper(beam, controls=("T", "E"))
    layer = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", rtol=TIGHT))
    T = torch.as_tensor(prob.interpolate(downward(BEAM_LOAD, 2), "T")).requires_grad_()
    E = torch.as_tensor(prob.interpolate(lambda x: 1.0 + 0.5 * x[0], "E")).requires_grad_()
    # Converged to 1e-12: the central differences of gradcheck (eps 1e-6) see no solver noise.
    assert torch.autograd.gradcheck(lambda T, E: layer(T=T, E=E), (T, E))


def test_hyperelastic_unrolled_gradcheck_of_capped_map(beam):
    """Two plain Newton steps from zero (not converged): the unrolled derivative is that map's exact one."""
    prob = hyper(beam, controls=("T", "E"))
    options = NewtonOptions(snes_type="newton", max_it=2, ksp="lu")
    layer = NonlinearSolveLayer(prob, options, diff="unrolled")
    T = torch.as_tensor(prob.interpolate(downward(BEAM_LOAD, 2), "T")).requires_grad_()
    E = torch.as_tensor(prob.interpolate(lambda x: 1.0 + 0.5 * x[0], "E")).requires_grad_()
    u = layer(T=T, E=E)
    assert layer.stats.last_newton.steps == 2 and layer.stats.last_newton.capped
    # Two steps leave Newton far from converged, so this is a different map from the solution's.
    converged = NonlinearSolveLayer(prob, NewtonOptions(snes_type="newton", rtol=TIGHT))(T=T, E=E)
    assert relative_max(u.detach().numpy(), converged.detach().numpy()) > 1e-2
    assert torch.autograd.gradcheck(lambda T, E: layer(T=T, E=E), (T, E))


# ------------------------------------------------------------------ hyperelasticity: failure
# SNES's reason for a NaN residual: DIVERGED_FNORM_NAN up to PETSc 3.2x, DIVERGED_FUNCTION_NANORINF after.
NAN_REASONS = {"DIVERGED_FNORM_NAN", "DIVERGED_FUNCTION_NANORINF"} & set(SNES_REASON_NAMES.values())


@pytest.mark.parametrize("options, reasons", [
    (NewtonOptions(snes_type="newton"), NAN_REASONS),          # the full step inverts elements: ln J of J < 0
    # short bt steps
    (NewtonOptions(snes_type="newtonls", converged_max_it=5), {"DIVERGED_MAX_IT", "DIVERGED_LINE_SEARCH"}),
])
def test_hyperelastic_overload_raises_with_snes_reason(beam, options, reasons):
    prob = hyper(beam)
    layer = NonlinearSolveLayer(prob, options)
    with pytest.raises(SolverFailedError) as info:
        layer(T=torch.as_tensor(prob.interpolate(downward(100 * BEAM_LOAD, 2), "T")))
    stats = info.value.stats
    assert stats.reason < 0 and not stats.ok and stats.reason_name in reasons
    assert f"SNES reason {stats.reason_name}" in str(info.value)
    if reasons is NAN_REASONS:       # named as what it is on every PETSc version
        assert "the residual became NaN or inf" in str(info.value) and stats.nonfinite_residual


# ------------------------------------------------------------------ Navier-Stokes
def test_cavity_newton_converges_quadratically_and_equals_dolfinx(cavity):
    prob = lid_flow(cavity, nu=CAVITY_NU)
    assert prob.enclosed
    layer = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT, snes_type="newtonls"))   # from zero, bt
    x = layer(f=torch.zeros(prob.control_size("f"), dtype=torch.float64)).numpy()
    stats = layer.stats.last_newton
    ratios = asymptotic_ratios(stats.residual_norms)
    assert len(ratios) >= 2 and max(ratios) < 10.0, stats.residual_norms
    # Every step is orthogonal to the constant pressure, so the pressure keeps the zero sum of the start.
    fields = prob.split(x)
    assert abs(fields["p"].sum()) < 1e-12 * np.abs(fields["p"]).sum()

    reference = lid_flow(cavity, nu=CAVITY_NU, controls=())
    x_ref = dolfinx_newton(reference)
    ref = reference.split(x_ref)
    ref["p"] = ref["p"] - ref["p"].mean()        # DOLFINx's pressure constant is MUMPS's choice
    bounds = newton_error_bound(reference, x), newton_error_bound(reference, x_ref)
    assert max(bounds) < 1e-11 * np.abs(x_ref).max(), bounds
    assert relative_max(fields["u"], ref["u"]) < 1e-10
    assert relative_max(fields["p"], ref["p"]) < 1e-10
    # A flow with inertia: the primary vortex is pushed downstream of the Stokes one (antisymmetric in x).
    u_stokes = SolveLayer(forms.stokes.problem(cavity, controls=(), velocity={"lid": (1.0, 0.0), "walls": 0.0}))()
    assert relative_max(fields["u"], prob.split(u_stokes.numpy())["u"]) > 0.05


def test_navier_stokes_reproduces_an_exact_flow(cavity):
    """u = (x + y, -y), p = 0 solves -nu Δu + (u·∇)u + ∇p = f, div u = 0 with f = (u·∇)u = (x, y), and
    lies in the Taylor-Hood space, so the discrete solution is exact. grad u is not symmetric:
    (∇u)^T u = (x + y, x + 2y) would be a different force, so the convection term's form is checked."""
    prob = forms.navier_stokes.problem(cavity, controls=("f",), nu=0.1,
                                       velocity={None: lambda x: np.vstack([x[0] + x[1], -x[1]])})
    layer = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT))
    x = layer(f=torch.as_tensor(prob.interpolate(lambda x: np.vstack([x[0], x[1]]), "f"))).numpy()
    fields = prob.split(x)
    exact = prob.interpolate(lambda x: np.vstack([x[0] + x[1], -x[1]]), "f")     # f lives on the velocity space
    assert layer.stats.last_newton.steps >= 3                   # from zero: a real Newton solve
    assert relative_max(fields["u"], exact) < 1e-10
    assert np.abs(fields["p"]).max() < 1e-10


def test_cavity_small_reynolds_limit_is_stokes(cavity):
    """Lid speed s at fixed nu: u(s) = s u_Stokes + O(s^2) (same signs and scaling as forms.stokes)."""
    stokes = forms.stokes.problem(cavity, controls=(), nu=CAVITY_NU, velocity={"lid": (1.0, 0.0), "walls": 0.0})
    x_stokes = SolveLayer(stokes)().numpy()
    gaps = []
    for s in (2e-3, 1e-3):
        prob = lid_flow(cavity, speed=s, nu=CAVITY_NU, controls=())
        x = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT))().numpy()
        gaps.append(np.linalg.norm(x - s * x_stokes) / np.linalg.norm(s * x_stokes))
    assert gaps[0] < 0.01
    assert 1.8 < gaps[0] / gaps[1] < 2.2


def test_cavity_implicit_gradient_matches_central_differences(cavity):
    """dL/df . d against (L(f + h d) - L(f - h d)) / 2h for L = <g, x(f)>, g and d random; g weights the
    pressure too, so the adjoint's treatment of the pressure constant is checked."""
    prob = lid_flow(cavity, nu=CAVITY_NU)
    layer = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT))
    gen = torch.Generator().manual_seed(7)
    f = torch.as_tensor(prob.interpolate(smooth_force, "f")).requires_grad_()
    d = torch.randn(f.shape, generator=gen, dtype=torch.float64)
    d = d / d.abs().max()
    g = torch.randn(prob.output_size, generator=gen, dtype=torch.float64)
    (g @ layer(f=f)).backward()
    implicit = float(f.grad @ d)
    # Central differences: error h^2 / 6 |L'''| + (solution error ~ 1e-15) / h; h = 1e-4 makes both far
    # below 1e-5 relative for a solution that varies on the scale of f ~ 1.
    h = 1e-4
    with torch.no_grad():
        fd = float(g @ layer(f=f + h * d) - g @ layer(f=f - h * d)) / (2 * h)
    assert abs(implicit) > 1e-3
    assert abs(fd - implicit) < 1e-5 * abs(implicit), (fd, implicit)


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("kwargs, error, match", [
    ({"controls": ("f",)}, ValueError, r"unknown control\(s\) \['f'\]; allowed controls are \['T', 'B', 'E'\]"),
    ({"nu": 0.5}, ValueError, r"nu must be a Poisson's ratio in \[0, 0.5\)"),
    ({"nu": -0.1}, ValueError, "Poisson's ratio"),
    ({"E": -1.0}, ValueError, r"E must be > 0 everywhere"),
    ({"E_space": "P2"}, ValueError, r"E_space must be one of \['P1', 'DG0'\]"),
    ({"T_space": "DG0"}, ValueError, "T_space must be 'P1'"),
    ({"T": (1.0, 2.0, 3.0)}, ValueError, "T must have 2 finite components"),
    ({"degree": 0}, ValueError, "degree must be an int >= 1"),
    ({"dirichlet": "bottom"}, ValueError, r"dirichlet=\['bottom'\]: label must be one of \['left', 'rest', 'right'\]"),
    ({"traction_on": 9}, ValueError, r"traction_on facet tag\(s\) \[9\] do not occur in the mesh"),
    ({"traction_on": lambda x: x[0] > 5.0}, ValueError, "traction_on's marker selects no boundary facet"),
    ({"traction_on": "left"}, ValueError, "every loaded facet is also clamped"),
    ({"dirichlet": ()}, ValueError, "dirichlet must be None, facet tags"),
    ({"dirichlet": 1.5}, ValueError, "dirichlet must be None, facet tags"),
])
def test_hyperelasticity_bad_input(beam, kwargs, error, match):
    with pytest.raises(error, match=match):
        hyper(beam, **kwargs)


def test_hyperelasticity_needs_a_body(beam):
    with pytest.raises(ValueError, match="needs facet tags, but this mesh has none"):
        forms.hyperelasticity.problem(beam.mesh, dirichlet="left")
    line = dolfinx.mesh.create_unit_interval(MPI.COMM_WORLD, 4)
    with pytest.raises(ValueError, match="needs a 2D or 3D body"):
        forms.hyperelasticity.problem(line)


@pytest.mark.parametrize("kwargs, error, match", [
    ({"controls": ("w",)}, ValueError, r"unknown control\(s\) \['w'\]; allowed controls are \['f', 'nu'\]"),
    ({"nu": 0.0}, ValueError, "nu must be a positive finite number"),
    ({"nu": -1e-2}, ValueError, "nu must be a positive finite number"),
    ({"nu": float("nan")}, ValueError, "nu must be a positive finite number"),
    ({"nu_space": "P2"}, ValueError, r"nu_space must be one of \['P1', 'DG0'\]"),
    ({"degree": 1}, ValueError, r"degree must be an int >= 2 \(Taylor-Hood"),
    ({"velocity": "lid"}, TypeError, "velocity must be a mapping"),
    ({"velocity": {"inlet": 1.0}}, ValueError, r"label must be one of \['lid', 'walls'\]"),
    ({"f": (1.0,)}, ValueError, "f must have 2 finite components"),
])
def test_navier_stokes_bad_input(cavity, kwargs, error, match):
    with pytest.raises(error, match=match):
        forms.navier_stokes.problem(cavity, **kwargs)


def test_navier_stokes_viscosity_control(cavity):
    """nu as a DG0 control (one value per cell): a constant field gives the constant-nu solution, and
    the implicit gradient in nu (a Jacobian control) matches central differences."""
    prob = lid_flow(cavity, nu=CAVITY_NU, controls=("nu",))
    assert "nu" not in prob.constants and prob.control_size("nu") == 128
    layer = NonlinearSolveLayer(prob, NewtonOptions(rtol=TIGHT))
    nu = torch.full((prob.control_size("nu"),), CAVITY_NU, dtype=torch.float64, requires_grad=True)
    x = layer(nu=nu)
    constant = lid_flow(cavity, nu=CAVITY_NU, controls=())
    x_const = NonlinearSolveLayer(constant, NewtonOptions(rtol=TIGHT))()
    assert relative_max(x.detach().numpy(), x_const.numpy()) < 1e-10

    gen = torch.Generator().manual_seed(3)
    d = CAVITY_NU * torch.rand(nu.shape, generator=gen, dtype=torch.float64)    # keeps nu + h d > 0
    g = torch.randn(prob.output_size, generator=gen, dtype=torch.float64)
    (g @ x).backward()
    implicit = float(nu.grad @ d)
    h = 1e-4                                   # relative step 1e-4 in nu: truncation ~1e-8, noise ~1e-11
    with torch.no_grad():
        fd = float(g @ layer(nu=nu + h * d) - g @ layer(nu=nu - h * d)) / (2 * h)
    assert abs(fd - implicit) < 1e-5 * abs(implicit), (fd, implicit)
