"""A backward uses exactly what its forward read: every mutable input a problem's forms read, changed
between a forward and its backward or between the calls of a multi-call loop, leaves each call's gradient
the one with nothing changed.

The mutable inputs are found from the forms themselves (UFL's coefficients and constants, the Dirichlet
values), not from the call record under test: each Constant, each fixed Function, each control a call
leaves out, and each boundary value. Every form module is covered with a converged solve (LU; Newton to
its tolerance), so the gradients must agree to round-off; a custom Problem is built as docs/api/problem.md
shows (``dirichletbc(PETSc.ScalarType(0.0), dofs, V)``: a C++ Constant whose value has no setter)."""
from __future__ import annotations

from mpi4py import MPI
import dolfinx
import numpy as np
import pytest
import torch
import ufl
from petsc4py import PETSc

from fempdl import NonlinearSolveLayer, Problem, Rollout, SolveLayer, forms, mesh
from fempdl.ksp_adjoint import KSPOptions
from fempdl.solve.newton_options import NewtonOptions

BATCH = 2
#: Control values scaled by name (a traction small enough for Newton from zero); others near 1.
SCALE = {"T": 2e-4, "f": 0.5}


@pytest.fixture(scope="module")
def square():
    return mesh.load("lshape", MPI.COMM_WORLD, h=0.3)


def custom_problem(msh):
    """Reaction-diffusion -div(kappa grad u) + c u = f, u = 0 on the boundary, as the docs build it."""
    V = (dolfinx.fem.functionspace(msh.mesh, ("Lagrange", 1)) if hasattr(dolfinx.fem, "functionspace")
         else dolfinx.fem.FunctionSpace(msh.mesh, ("Lagrange", 1)))
    kappa, f, c = dolfinx.fem.Function(V), dolfinx.fem.Function(V), dolfinx.fem.Constant(msh.mesh, 10.0)
    kappa.x.array[:] = 1.0
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    tdim = msh.mesh.topology.dim
    msh.mesh.topology.create_connectivity(tdim - 1, tdim)
    dofs = dolfinx.fem.locate_dofs_topological(V, tdim - 1, dolfinx.mesh.exterior_facet_indices(msh.mesh.topology))
    bc = dolfinx.fem.dirichletbc(PETSc.ScalarType(0.0), dofs, V)
    return Problem((kappa * ufl.inner(ufl.grad(u), ufl.grad(v)) + c * u * v) * ufl.dx, f * v * ufl.dx, [bc],
                   controls={"kappa": kappa, "f": f})


def beam():
    """A soft beam [0, 4] x [0, 1], clamped at x = 0 (the hyperelastic form's default faces)."""
    return dolfinx.mesh.create_rectangle(MPI.COMM_WORLD, [np.zeros(2), np.array([4.0, 1.0])], [8, 2])


#: name -> problem builder: each form with its default controls or, where the default is a single one,
#: one more, so that a call can leave one out.
LINEAR = {
    "poisson": lambda m: forms.poisson.problem(m, controls=("f", "kappa")),
    "heat": lambda m: forms.heat.problem(m, controls=("u0", "f", "kappa"), dt=0.05),
    "elasticity": lambda m: forms.elasticity.problem(m, controls=("f", "E")),
    "stokes": lambda m: forms.stokes.problem(m),
    "oseen": lambda m: forms.oseen.problem(m),
    "burgers": lambda m: forms.burgers.problem(m),
    "transport": lambda m: forms.transport.problem(m),
    "custom": custom_problem,
}
NONLINEAR = {
    "nonlinear_diffusion": lambda m: forms.nonlinear_diffusion.problem(m, controls=("f", "kappa"), alpha=0.5),
    "hyperelasticity": lambda m: forms.hyperelasticity.problem(beam(), controls=("T", "E")),
    "navier_stokes": lambda m: forms.navier_stokes.problem(m, controls=("f", "nu"), nu=1.0),
}


def layer_for(name, problem):
    if name in NONLINEAR:
        return NonlinearSolveLayer(problem, NewtonOptions(ksp="lu"))
    return SolveLayer(problem, "lu")


def control_batches(problem, names, seed=0):
    gen = torch.Generator().manual_seed(seed)
    return {n: SCALE.get(n, 1.0) * (1.0 + 0.2 * torch.rand(BATCH, problem.control_size(n), dtype=torch.float64,
                                                              generator=gen)) for n in names}


def mutable_inputs(problem):
    """(label, object) for every value the forms read besides the call's controls: found from UFL."""
    forms_ = (problem.F,) if hasattr(problem, "F") else (problem.a, problem.L)
    work = {id(getattr(problem, n)) for n in ("u", "lam", "step") if hasattr(problem, n)}
    controls = {id(problem.control(n)) for n in problem.control_names}
    found = {}
    for form in forms_:
        for obj in (*form.coefficients(), *form.constants()):
            if id(obj) not in work | controls:
                found.setdefault(id(obj), (f"{type(obj).__name__} {obj}", obj))
    for i, bc in enumerate(problem.bcs):
        g = bc.g
        if (hasattr(g, "x") or hasattr(g, "value")) and id(g) not in work | controls:
            found.setdefault(id(g), (f"boundary value {i}", g))
    return list(found.values())


def mutate(obj):
    """Change ``obj``'s values (a Function's array, a Constant's value) by about 20%, a zero one a little (a
    body force on the soft beam), and return how to undo it."""
    if hasattr(obj, "x"):
        saved = obj.x.array.copy()
        obj.x.array[:] = 1.2 * saved + (0.05 * np.abs(saved).max() if saved.any() else 1e-4)
        return lambda: obj.x.array.__setitem__(slice(None), saved)
    saved = np.array(obj.value, dtype=np.float64)
    view = obj.value
    view[...] = 1.2 * saved + 1e-4 * (saved == 0)          # a Poisson ratio 0.3 stays below 0.5
    return lambda: obj.value.__setitem__(Ellipsis, saved)


def gradients(layer, inputs, weights):
    for t in inputs.values():
        t.grad = None
    (layer(**inputs) * weights).sum().backward()
    return {n: t.grad.clone() for n, t in inputs.items()}


def close(a, b):
    return all(torch.linalg.norm(a[n] - b[n]) <= 1e-9 * torch.linalg.norm(b[n]) + 1e-14 for n in b)


CASES = [pytest.param(name, build, id=name) for name, build in {**LINEAR, **NONLINEAR}.items()]


@pytest.mark.parametrize("name,build", CASES)
def test_every_mutable_input_changed_leaves_each_calls_gradient(square, name, build):
    problem = build(square)
    layer = layer_for(name, problem)
    names = list(problem.control_names)
    values = control_batches(problem, names)
    gen = torch.Generator().manual_seed(1)
    w1, w2 = (torch.rand(BATCH, problem.output_size, dtype=torch.float64, generator=gen) for _ in range(2))
    targets = [(label, obj, names) for label, obj in mutable_inputs(problem)]
    # Each control left out of the call in turn, read from its Function, which the loop changes.
    for left_out in names if len(names) > 1 else ():
        kept = [n for n in names if n != left_out]
        problem.control(left_out).x.array[:] = values[left_out][0].mean().item()
        targets.append((f"left-out control {left_out}", problem.control(left_out), kept))
    assert len(targets) >= 2
    for label, obj, called in targets:
        inputs = {n: values[n].clone().requires_grad_() for n in called}
        g_ref = gradients(layer, inputs, w1)
        # Changed between a forward and its backward.
        for t in inputs.values():
            t.grad = None
        y = layer(**inputs)
        undo = mutate(obj)
        (y * w1).sum().backward()
        undo()
        assert close({n: t.grad for n, t in inputs.items()}, g_ref), f"{name}: {label} between forward and backward"
        # Changed between two calls with the same controls, both backpropagated at the end.
        undo = mutate(obj)
        g_changed = gradients(layer, inputs, w2)
        undo()
        for t in inputs.values():
            t.grad = None
        y1 = layer(**inputs)
        undo = mutate(obj)
        y2 = layer(**inputs)
        undo()
        ((y1 * w1).sum() + (y2 * w2).sum()).backward()
        both = {n: g_ref[n] + g_changed[n] for n in g_ref}
        assert close({n: t.grad for n, t in inputs.items()}, both), f"{name}: {label} between two calls"


def heat_loop_layer(square):
    return SolveLayer(forms.heat.problem(square, controls=("u0", "kappa"), dt=0.01), "lu")


def fixed_dt_gradient(square, u, kappa, dts, options="lu", weights=None):
    """The gradient of the last state after one call per dt, each by its own layer at a fixed dt."""
    kappa = kappa.clone().requires_grad_()
    for dt in dts:
        u = SolveLayer(forms.heat.problem(square, controls=("u0", "kappa"), dt=dt), options)(u0=u, kappa=kappa)
    (u if weights is None else u * weights).sum().backward()
    return kappa.grad


@pytest.mark.parametrize("dts,options", [((0.05, 0.02, 0.08), "lu"),
                                         ((0.05, 0.02, 0.08), KSPOptions.preset("jacobi", max_it=5)),
                                         ((0.05, 0.02, 0.08, 0.03, 0.06, 0.01), "lu")],
                         ids=["3-lu", "3-jacobi5", "6-lu"])
def test_one_layer_called_per_time_step_with_dt_set_before_each_call(square, dts, options):
    # The repro: per-sample kappa, the same in every call; only dt differs. Before, an earlier
    # call's adjoint took a later call's matrix (33-50% off; more calls than the 4 kept: 42%).
    layer = SolveLayer(forms.heat.problem(square, controls=("u0", "kappa"), dt=0.01), options)
    values = control_batches(layer.problem, ["u0", "kappa"])
    u, kappa = values["u0"], values["kappa"].clone().requires_grad_()
    for dt in dts:
        layer.problem.constants["dt"].value = dt
        u = layer(u0=u, kappa=kappa)
    u.sum().backward()
    expected = fixed_dt_gradient(square, values["u0"], values["kappa"], dts, options)
    assert torch.linalg.norm(kappa.grad - expected) <= 1e-10 * torch.linalg.norm(expected)


@pytest.mark.parametrize("schedule", [None, "autograd", "all", ("revolve", 1), ("multistage", 1, 1)],
                         ids=["steps", "autograd", "all", "revolve", "multistage"])
@pytest.mark.parametrize("constants_as", ["list", "array", "tensor"])
def test_a_rollout_reads_its_own_dts_after_other_calls_and_in_place_edits(square, schedule, constants_as):
    # An earlier training call of the step layer with the same kappa kept its matrices (544% off before);
    # the per-step dts, given as an array or a tensor, are edited in place after the forward (15-64%).
    dts = (0.05, 0.02, 0.08)
    layer = heat_loop_layer(square)
    values = control_batches(layer.problem, ["u0", "kappa"])
    kappa = values["kappa"].clone().requires_grad_()
    layer(u0=values["u0"], kappa=kappa).sum().backward()
    kappa.grad = None
    given = {"list": list(dts), "array": np.array(dts), "tensor": torch.tensor(dts, dtype=torch.float64)}[constants_as]
    rollout = Rollout(layer) if schedule is None else Rollout(layer, schedule=schedule)
    states = rollout(values["u0"], steps=len(dts), constants={"dt": given}, kappa=kappa)
    if constants_as != "list":
        given[:] = 0.5
    states[:, -1].sum().backward()
    expected = fixed_dt_gradient(square, values["u0"], values["kappa"], dts)
    assert torch.linalg.norm(kappa.grad - expected) <= 1e-10 * torch.linalg.norm(expected)


def test_a_parameter_kappa_through_a_rollout(square):
    # An nn.Parameter sends a plain Rollout down the per-step path: one step layer call per step.
    dts = (0.05, 0.02, 0.08)
    layer = heat_loop_layer(square)
    values = control_batches(layer.problem, ["u0", "kappa"])
    kappa = torch.nn.Parameter(values["kappa"].clone())
    Rollout(layer)(values["u0"], steps=3, constants={"dt": list(dts)}, kappa=kappa)[:, -1].sum().backward()
    expected = fixed_dt_gradient(square, values["u0"], values["kappa"], dts)
    assert torch.linalg.norm(kappa.grad - expected) <= 1e-10 * torch.linalg.norm(expected)


def test_the_docs_custom_problem_backward_where_its_state_must_be_put_back(square):
    # dirichletbc(PETSc.ScalarType(0.0), ...) holds a C++ Constant with no value setter; a two-call loop
    # that changes c between the calls made the backward restore it (AttributeError before).
    problem = custom_problem(square)
    layer = SolveLayer(problem, "lu")
    c = next(obj for obj in problem.a.constants())
    f = control_batches(problem, ["f"])["f"].requires_grad_()
    y1 = layer(f=f)
    c.value = 20.0
    y2 = layer(f=f)
    (y1.sum() + y2.sum()).backward()
    g = f.grad.clone()
    f.grad = None
    c.value = 10.0
    layer(f=f).sum().backward()
    c.value = 20.0
    layer(f=f).sum().backward()
    assert torch.linalg.norm(f.grad - g) <= 1e-10 * torch.linalg.norm(g)
    assert float(c.value) == 20.0                   # the backward put back what the loop had set
