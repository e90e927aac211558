"""Bad inputs and failed solves: every one raises (or warns) with a message that
names the argument, what was received and what to do.

Covers SolveLayer.forward inputs, KSPOptions validation, Problem / forms
construction, solver failures (raise / warn, counting, restoring the control
Functions) and the layer's state after a failure. Small meshes only.
"""
import re
import warnings

from mpi4py import MPI
import dolfinx.fem
import dolfinx.mesh
import numpy as np
import pytest
import torch
import ufl

from fempdl import Problem, forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import _dolfinx
from fempdl.ksp_adjoint import KSPOptions, SolverFailedError

COMM = MPI.COMM_WORLD
F64 = torch.float64

# Solver configurations that reliably fail on the 8x8 Poisson problem below,
# with the kappa (DG0) that makes them fail and the message fragment expected.
#   name -> (KSPOptions kwargs, kappa kind, message regex, PETSc reason name or None)
FAILING = {
    # Richardson without preconditioner, step 10: |1 - 10 lambda| > 1, overflows to inf/NaN.
    "nan": (dict(ksp_type="richardson", pc_type="none", max_it=2000,
                 petsc_options={"ksp_richardson_scale": 10.0}),
            "ones", r"richardson\+none solve produced NaN or inf; check the inputs", None),
    # Same iteration with a divergence test: stops after a few iterations.
    "dtol": (dict(ksp_type="richardson", pc_type="none", max_it=200, divtol=1e3,
                  petsc_options={"ksp_richardson_scale": 10.0}),
             "ones", r"richardson\+none solve stopped with DIVERGED_DTOL after \d+ iterations",
             "DIVERGED_DTOL"),
    # CG on an indefinite operator (kappa = -1 for x < 1/2, +1 elsewhere). (A negative
    # definite one, kappa = -1 everywhere, is fine for CG: PETSc checks for a sign change.)
    "indefinite": (dict(ksp_type="cg", pc_type="none", max_it=None),
                   "sign_change", r"cg\+none solve stopped with DIVERGED_INDEFINITE_MAT after \d+ iterations",
                   "DIVERGED_INDEFINITE_MAT"),
    # CG + Jacobi with kappa changing sign: indefinite preconditioner.
    "indefinite_pc": (dict(ksp_type="cg", pc_type="jacobi", max_it=None),
                      "sign_change", r"cg\+jacobi solve stopped with DIVERGED_INDEFINITE_PC after \d+ iterations",
                      "DIVERGED_INDEFINITE_PC"),
    # Converged mode (max_it=None) on an indefinite operator: Richardson-Jacobi never reaches rtol.
    "unconverged": (dict(ksp_type="richardson", pc_type="jacobi", max_it=None),
                    "sign_change", r"richardson\+jacobi solve did not reach rtol=1e-10 in 10000 iterations",
                    "DIVERGED_MAX_IT"),
}


# ---------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def msh():
    return dolfinx.mesh.create_unit_square(COMM, 8, 8)


@pytest.fixture(scope="module")
def prob(msh):
    """Poisson, controls f (P1) and kappa (DG0); defaults f = kappa = 1."""
    prob = forms.poisson.problem(msh, controls=("f", "kappa"), kappa_space="DG0")
    prob.positive = ()          # kappa <= 0 on purpose: these tests reach the solver's own failures
    return prob


@pytest.fixture(scope="module")
def layer(prob):
    lay = SolveLayer(prob, KSPOptions(max_it=10))
    yield lay
    lay.close()


@pytest.fixture(scope="module")
def nf(prob):
    return prob.control_size("f")


@pytest.fixture(scope="module")
def nk(prob):
    return prob.control_size("kappa")


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", h=0.5)


def kappa_values(prob, kind: str) -> torch.Tensor:
    nk = prob.control_size("kappa")
    if kind == "ones":
        return torch.ones(nk, dtype=F64)
    if kind == "minus_ones":
        return -torch.ones(nk, dtype=F64)
    if kind == "zeros":
        return torch.zeros(nk, dtype=F64)
    if kind == "sign_change":
        x = torch.as_tensor(prob.dof_coordinates("kappa")[:, 0])
        return torch.where(x < 0.5, -1.0, 1.0).to(F64)
    raise AssertionError(kind)


def reference_solution(prob, f, kappa) -> torch.Tensor:
    """A converged LU solve on a fresh layer."""
    ref = SolveLayer(prob, "lu")
    try:
        return ref(f=f, kappa=kappa)
    finally:
        ref.close()


# ============================================================ SolveLayer inputs
@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_control_names_control_and_count(layer, nf, bad):
    f = torch.ones(2, nf, dtype=F64)
    f[0, 3] = f[1, 5] = f[1, 7] = bad
    with pytest.raises(ValueError, match=r"control 'f' contains 3 NaN/inf value\(s\); check the upstream"):
        layer(f=f)


def test_nonfinite_second_control_float32(layer, nf, nk):
    kappa = torch.ones(nk, dtype=torch.float32)
    kappa[0] = float("nan")
    kappa[-1] = float("inf")
    with pytest.raises(ValueError, match=r"control 'kappa' contains 2 NaN/inf value\(s\)"):
        layer(f=torch.ones(nf, dtype=torch.float32), kappa=kappa)


def test_wrong_last_dim(layer, nf):
    msg = (re.escape(f"control 'f' has shape (2, {nf + 1}), expected (B, {nf}) or ({nf},)")
           + r".*control_size\('f'\)")
    with pytest.raises(ValueError, match=msg):
        layer(f=torch.ones(2, nf + 1, dtype=F64))


def test_three_dimensional_tensor(layer, nf):
    with pytest.raises(ValueError, match=re.escape(f"control 'f' has shape (2, 3, {nf}), expected (B, {nf})")):
        layer(f=torch.ones(2, 3, nf, dtype=F64))


@pytest.mark.parametrize("shape", [(), (0,)])
def test_scalar_and_empty_vector(layer, nf, shape):
    with pytest.raises(ValueError, match=re.escape(f"control 'f' has shape {shape}, expected (B, {nf}) or ({nf},)")):
        layer(f=torch.ones(shape, dtype=F64))


@pytest.mark.parametrize("other", ["mesh", "degree"])
def test_tensor_for_another_mesh_or_degree(layer, prob, msh, other):
    if other == "mesh":
        other_prob = forms.poisson.problem(dolfinx.mesh.create_unit_square(COMM, 4, 4), controls=("f",))
    else:
        other_prob = forms.poisson.problem(msh, controls=("f",), degree=2)
    n_other = other_prob.control_size("f")
    assert n_other != prob.control_size("f")
    with pytest.raises(ValueError, match=r"another mesh, space or degree \(see problem\.control_size\('f'\)\)"):
        layer(f=torch.ones(3, n_other, dtype=F64))


def test_unknown_control_lists_allowed(layer, nf):
    with pytest.raises(ValueError, match=r"unknown control\(s\) \['g'\]; this layer's controls are \['f', 'kappa'\]"):
        layer(f=torch.ones(nf, dtype=F64), g=torch.ones(nf, dtype=F64))


@pytest.mark.parametrize("dtype", [torch.int64, torch.int32, torch.complex128, torch.bool, torch.float16])
def test_non_float_dtype(layer, nf, dtype):
    with pytest.raises(TypeError, match=re.escape(f"control 'f' has dtype {dtype}; use float32 or float64")):
        layer(f=torch.ones(nf, dtype=dtype))


@pytest.mark.parametrize("value, type_name", [(np.ones(81), "ndarray"), ([1.0] * 81, "list"), (1.0, "float")])
def test_non_tensor(layer, nf, value, type_name):
    assert nf == 81
    with pytest.raises(TypeError, match=rf"control 'f' must be a torch\.Tensor, got {type_name}; "
                                        r"wrap arrays with torch\.as_tensor"):
        layer(f=value)


def test_inconsistent_batch_sizes(layer, nf, nk):
    with pytest.raises(ValueError, match=r"controls have different batch sizes \{'f': 2, 'kappa': 3\}"):
        layer(f=torch.ones(2, nf, dtype=F64), kappa=torch.ones(3, nk, dtype=F64))


def test_empty_batch(layer, nf):
    with pytest.raises(ValueError, match=re.escape(f"control 'f' has an empty batch (shape (0, {nf}))")):
        layer(f=torch.ones(0, nf, dtype=F64))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU to put controls on two devices")
def test_controls_on_different_devices(layer, nf, nk):
    with pytest.raises(ValueError, match=r"controls are on different devices"):
        layer(f=torch.ones(nf, dtype=F64), kappa=torch.ones(nk, dtype=F64, device="cuda"))


def test_bad_inputs_solve_nothing_and_touch_nothing(prob, nf, nk):
    """Validation happens before any solve: no solve is counted, no control Function changes."""
    lay = SolveLayer(prob, KSPOptions(max_it=10))
    before = {n: prob.control(n).x.array.copy() for n in prob.control_names}
    bad_calls = [
        dict(f=torch.full((2, nf), float("nan"), dtype=F64)),
        dict(f=torch.ones(2, nf, dtype=F64), kappa=torch.ones(3, nk, dtype=F64)),
        dict(f=torch.ones(2, nf, dtype=F64), kappa=torch.ones(2, nk + 1, dtype=F64)),
        dict(f=torch.ones(nf, dtype=F64), kappa=torch.ones(nk, dtype=torch.int64)),
    ]
    try:
        for kwargs in bad_calls:
            with pytest.raises((ValueError, TypeError)):
                lay(**kwargs)
        assert lay.stats.forward_solves == 0
        assert lay.stats.forward_iterations == 0
        for n, arr in before.items():
            np.testing.assert_array_equal(prob.control(n).x.array, arr)
        # and a good call still runs exactly max_it iterations per sample
        lay(f=torch.ones(2, nf, dtype=F64))
        assert lay.stats.forward_solves == 2
        assert lay.stats.forward_iterations == 20
    finally:
        lay.close()


def test_layer_constructor_errors(prob):
    with pytest.raises(TypeError, match=r"problem must be a fempdl\.Problem, got str"):
        SolveLayer("poisson")
    with pytest.raises(TypeError, match=r"options must be KSPOptions or a preset name, got int"):
        SolveLayer(prob, 5)
    with pytest.raises(ValueError, match=r"unknown preset 'nonexistent'; choose one of \['amg', 'cg', 'cholesky', "
                                         r"'gmres', 'gmres-ilu', 'jacobi', 'lu', 'lu-lagged', 'schur'\]"):
        SolveLayer(prob, "nonexistent")
    with pytest.raises(ValueError, match=r"diff must be one of \[.*'implicit'.*\], got 'bogus'"):
        SolveLayer(prob, diff="bogus")


# ================================================================= KSPOptions
KSP_BAD = [
    (dict(max_it=0), ValueError, r"max_it must be >= 1, got 0; use max_it=None to run to rtol"),
    (dict(max_it=-3), ValueError, r"max_it must be >= 1, got -3"),
    (dict(max_it=2.5), TypeError, r"max_it must be an int, got 2\.5"),
    (dict(max_it=True), TypeError, r"max_it must be an int, got True"),
    (dict(ksp_type="foo"), ValueError, r"ksp_type='foo' is not a PETSc type; choose one of \[.*'gmres'.*'richardson'"),
    (dict(ksp_type="GMRES"), ValueError, r"ksp_type='GMRES' is not a PETSc type"),
    (dict(pc_type="bar"), ValueError, r"pc_type='bar' is not a PETSc type; choose one of \[.*'jacobi'"),
    (dict(ksp_type=3), TypeError, r"ksp_type must be a str, got 3"),
    (dict(rtol=1.5), ValueError, r"rtol must be in \[0, 1\), got 1\.5"),
    (dict(rtol=float("nan")), ValueError, r"rtol must be finite, got nan"),
    (dict(rtol="1e-5"), TypeError, r"rtol must be a float or None, got '1e-5'"),
    (dict(atol=-1), ValueError, r"atol must be >= 0, got -1"),
    (dict(divtol=0.5), ValueError, r"divtol must be > 1 \(a growth factor of the residual\), got 0\.5"),
    (dict(ksp_type="richardson", gmres_restart=10), ValueError,
     r"gmres_restart is only meaningful for \[.*'gmres'.*\], got ksp_type='richardson'; drop gmres_restart"),
    (dict(ksp_type="gmres", gmres_restart=0), ValueError, r"gmres_restart must be >= 1, got 0"),
    (dict(petsc_options={"-ksp_view": None}), ValueError,
     r"petsc_options keys are option names without the leading '-', got '-ksp_view'"),
    (dict(petsc_options={"ksp_max_it": 5}), ValueError,
     r"petsc_options\['ksp_max_it'\] conflicts with a KSPOptions field; set max_it instead"),
    (dict(petsc_options={"ksp_rtol": 1e-3}), ValueError,
     r"petsc_options\['ksp_rtol'\] conflicts with a KSPOptions field; set rtol instead"),
    (dict(petsc_options={"pc_type": "lu"}), ValueError, r"set pc_type instead"),
    (dict(petsc_options=[("ksp_view", None)]), TypeError,
     r"petsc_options must be a mapping of option name to value, got list"),
    (dict(petsc_options="ksp_view"), TypeError, r"petsc_options must be a mapping .*, got str"),
    (dict(petsc_options={"ksp_view": [1]}), TypeError,
     r"petsc_options\['ksp_view'\] must be str, number, bool or None, got \[1\]"),
    (dict(on_failure="ignore"), ValueError, r"on_failure must be 'raise' or 'warn', got 'ignore'"),
    (dict(ksp_type="preonly", pc_type="lu", max_it=5), ValueError,
     r"max_it=5 has no effect with ksp_type='preonly' \(a direct solve\); use max_it=None"),
    (dict(adjoint=KSPOptions(adjoint=KSPOptions())), ValueError,
     r"adjoint options must not have an adjoint of their own"),
    (dict(adjoint="jacobi"), TypeError, r"adjoint must be KSPOptions or None, got str"),
]


@pytest.mark.parametrize("kwargs, exc, match", KSP_BAD,
                         ids=[",".join(f"{k}={v!r}" for k, v in kw.items())[:60] for kw, _, _ in KSP_BAD])
def test_kspoptions_rejects(kwargs, exc, match):
    with pytest.raises(exc, match=match):
        KSPOptions(**kwargs)


def test_unknown_preset_and_bad_override():
    with pytest.raises(ValueError, match=r"unknown preset 'foo'; choose one of \['amg', 'cg', 'cholesky', 'gmres', "
                                         r"'gmres-ilu', 'jacobi', 'lu', 'lu-lagged', 'schur'\]"):
        KSPOptions.preset("foo")
    with pytest.raises(ValueError, match=r"max_it must be >= 1, got 0"):
        KSPOptions.preset("jacobi", max_it=0)
    with pytest.raises(ValueError, match=r"max_it=3 has no effect with ksp_type='preonly'"):
        KSPOptions.preset("lu", max_it=3)


def test_kspoptions_are_immutable():
    opts = KSPOptions(max_it=7, petsc_options={"ksp_richardson_scale": 0.8})
    with pytest.raises(AttributeError):
        opts.max_it = 3
    with pytest.raises(TypeError):
        opts.petsc_options["ksp_richardson_scale"] = 0.5
    assert opts.max_it == 7
    assert opts.petsc_options["ksp_richardson_scale"] == 0.8


@pytest.mark.parametrize("value, exc, match", [
    (0, ValueError, r"max_it must be >= 1, got 0"),
    (-3, ValueError, r"max_it must be >= 1, got -3"),
    (2.5, TypeError, r"max_it must be an int, got 2\.5"),
    (True, TypeError, r"max_it must be an int, got True"),
])
def test_setting_bad_max_it_keeps_previous_cap(prob, nf, value, exc, match):
    lay = SolveLayer(prob, KSPOptions(max_it=10))
    try:
        with pytest.raises(exc, match=match):
            lay.max_it = value
        assert lay.max_it == 10
        assert lay.options.max_it == 10
        assert lay._system._solver.ksp.getTolerances()[3] == 10
        lay(f=torch.ones(nf, dtype=F64))
        assert lay.stats.last.iterations == 10
        assert lay.stats.forward_iterations == 10
    finally:
        lay.close()


def test_setting_max_it_on_direct_solver_rejected(prob):
    lay = SolveLayer(prob, "lu")
    try:
        with pytest.raises(ValueError, match=r"max_it=5 has no effect with ksp_type='preonly'"):
            lay.max_it = 5
        assert lay.max_it is None
    finally:
        lay.close()


# ============================================================ Problem / forms
@pytest.mark.parametrize("pde, controls, match", [
    ("poisson", ("g",), r"poisson: unknown control\(s\) \['g'\]; allowed controls are \['f', 'kappa'\]"),
    ("poisson", ("f", "u0"), r"poisson: unknown control\(s\) \['u0'\]"),
    ("heat", ("kappa", "q"), r"heat: unknown control\(s\) \['q'\]; allowed controls are \['u0', 'f', 'kappa'\]"),
    ("poisson", ("f", "f"), r"poisson: controls \['f', 'f'\] contain duplicates"),
])
def test_forms_unknown_controls(msh, pde, controls, match):
    with pytest.raises(ValueError, match=match):
        getattr(forms, pde).problem(msh, controls=controls)


@pytest.mark.parametrize("theta", [1.5, -0.1, float("nan"), True])
def test_heat_theta_outside_unit_interval(msh, theta):
    with pytest.raises(ValueError, match=re.escape(f"theta must be in [0, 1], got {theta!r}")):
        forms.heat.problem(msh, theta=theta)


@pytest.mark.parametrize("dt", [0, 0.0, -0.1, float("inf"), float("nan")])
def test_heat_dt_not_positive(msh, dt):
    with pytest.raises(ValueError, match=re.escape(f"dt must be a positive finite number, got {dt!r}")):
        forms.heat.problem(msh, dt=dt)


@pytest.mark.parametrize("pde", ["poisson", "heat"])
def test_kappa_space_p2(msh, pde):
    with pytest.raises(ValueError, match=r"kappa_space must be one of \['P1', 'DG0'\], got 'P2'"):
        getattr(forms, pde).problem(msh, kappa_space="P2")


@pytest.mark.parametrize("pde", ["poisson", "heat"])
@pytest.mark.parametrize("degree", [0, -1, 1.0, True])
def test_bad_degree(msh, pde, degree):
    with pytest.raises(ValueError, match=re.escape(f"degree must be an int >= 1, got {degree!r}")):
        getattr(forms, pde).problem(msh, degree=degree)


@pytest.mark.parametrize("value, exc, match", [
    (float("nan"), ValueError, r"f must be finite, got nan"),
    ("one", TypeError, r"f must be a float or a callable x -> values, got str"),
    (lambda x: np.full(x.shape[1], np.nan), ValueError, r"f: the callable returned NaN or inf values"),
])
def test_bad_fixed_coefficient(msh, value, exc, match):
    with pytest.raises(exc, match=match):
        forms.poisson.problem(msh, f=value)


def test_poisson_without_dirichlet(msh):
    with pytest.raises(ValueError, match=r"poisson: dirichlet=\(\) leaves u determined only up to a constant; "
                                         r"give at least one Dirichlet boundary part"):
        forms.poisson.problem(msh, dirichlet=())


def test_dirichlet_unknown_tag_name(lshape):
    with pytest.raises(ValueError, match=r"one of \['outer', 'reentrant'\] for mesh 'lshape', got 'outr'"):
        forms.poisson.problem(lshape, dirichlet=("outr",))


def test_dirichlet_unknown_tag_name_names_dirichlet(lshape):
    with pytest.raises(ValueError, match=r"dirichlet"):
        forms.poisson.problem(lshape, dirichlet=("outr",))


def test_dirichlet_unknown_integer_tag(lshape):
    with pytest.raises(ValueError,
                       match=r"dirichlet facet tag\(s\) \[99\] do not occur in the mesh; tags present: \[1, 2\]"):
        forms.heat.problem(lshape, dirichlet=(1, 99))


def test_dirichlet_names_on_untagged_mesh(msh):
    with pytest.raises(ValueError, match=r"dirichlet=\['outer'\] needs facet tags, but this mesh has none"):
        forms.poisson.problem(msh, dirichlet="outer")


@pytest.fixture(scope="module")
def raw(msh):
    """UFL pieces for building Problems by hand."""
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)
    f = dolfinx.fem.Function(V, name="f")
    a = ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx
    L = f * v * ufl.dx
    return dict(V=V, u=u, v=v, f=f, a=a, L=L)


def test_control_function_not_in_forms(raw):
    g = dolfinx.fem.Function(raw["V"])
    with pytest.raises(ValueError, match=r"controls\['g'\] does not appear in a or L; use the same Function object"):
        Problem(raw["a"], raw["L"], (), controls={"f": raw["f"], "g": g})


def test_control_function_from_another_mesh(raw, msh):
    other = dolfinx.mesh.create_unit_square(COMM, 4, 4)
    h = dolfinx.fem.Function(_dolfinx.function_space(other, "Lagrange", 1))
    match = r"controls\['h'\] lives on a different mesh than the solution space; create it on the same mesh object"
    # not in the forms at all
    with pytest.raises(ValueError, match=match):
        Problem(raw["a"], raw["L"], (), controls={"h": h})
    # used in a (UFL accepts it when the measure names the domain)
    a2 = h * ufl.inner(ufl.grad(raw["u"]), ufl.grad(raw["v"])) * ufl.dx(domain=msh)
    with pytest.raises(ValueError, match=match):
        Problem(a2, raw["L"], (), controls={"h": h})


@pytest.mark.parametrize("name", ["my-f", "class", "2f", "", 1])
def test_control_name_not_identifier(raw, name):
    with pytest.raises(ValueError, match=re.escape(f"control names must be Python identifiers (they become "
                                                   f"keyword arguments of the layer), got {name!r}")):
        Problem(raw["a"], raw["L"], (), controls={name: raw["f"]})


def test_a_given_as_linear_form(raw):
    with pytest.raises(TypeError,
                       match=r"a must be a bilinear UFL form \(two arguments\), got a form with 1 argument\(s\)"):
        Problem(raw["L"], raw["L"], (), controls={"f": raw["f"]})
    with pytest.raises(TypeError,
                       match=r"L must be a linear UFL form \(one argument\), got a form with 2 argument\(s\)"):
        Problem(raw["a"], raw["a"], (), controls={"f": raw["f"]})
    with pytest.raises(TypeError, match=r"a must be a bilinear UFL form \(two arguments\), got float"):
        Problem(1.0, raw["L"])


def test_problem_bad_controls_and_bcs(raw):
    with pytest.raises(TypeError, match=r"controls must be a mapping \{name: dolfinx\.fem\.Function\}, got list"):
        Problem(raw["a"], raw["L"], (), controls=[raw["f"]])
    with pytest.raises(TypeError, match=r"controls\['f'\] must be a dolfinx\.fem\.Function, got float"):
        Problem(raw["a"], raw["L"], (), controls={"f": 1.0})
    with pytest.raises(TypeError, match=r"bcs\[0\] must be a dolfinx\.fem\.dirichletbc, got int"):
        Problem(raw["a"], raw["L"], [1], controls={"f": raw["f"]})


def test_problem_unknown_control_lookup(prob):
    with pytest.raises(ValueError, match=r"unknown control 'u0'; this problem's controls are \['f', 'kappa'\]"):
        prob.control_size("u0")


# ============================================================= solver failures
@pytest.mark.parametrize("case", sorted(FAILING))
def test_failure_raises_by_default(prob, nf, case):
    kwargs, kind, match, reason = FAILING[case]
    lay = SolveLayer(prob, KSPOptions(**kwargs))
    try:
        with pytest.raises(SolverFailedError, match=match) as info:
            lay(f=torch.ones(nf, dtype=F64), kappa=kappa_values(prob, kind))
        msg = str(info.value)
        # says what to do
        assert re.search(r"; (try|check) ", msg), msg
        assert "Pass on_failure='warn' to get the iterate with a warning instead." in msg
        assert info.value.stats.ok is False
        if reason is not None:
            assert info.value.stats.reason_name == reason
        assert lay.stats.failures == 1
        assert lay.stats.forward_solves == 1
        assert lay.stats.last is info.value.stats
    finally:
        lay.close()


@pytest.mark.parametrize("case", sorted(FAILING))
def test_failure_warns_with_on_failure_warn(prob, nf, case):
    kwargs, kind, match, _ = FAILING[case]
    lay = SolveLayer(prob, KSPOptions(**kwargs, on_failure="warn"))
    try:
        with pytest.warns(RuntimeWarning, match=match):
            u = lay(f=torch.ones(nf, dtype=F64), kappa=kappa_values(prob, kind))
        assert u.shape == (prob.output_size,)
        assert u.dtype == F64
        assert lay.stats.failures == 1
        assert lay.stats.last.ok is False
    finally:
        lay.close()


@pytest.mark.parametrize("on_failure", ["raise", "warn"])
@pytest.mark.parametrize("case", sorted(FAILING))
def test_never_nan_silently(prob, nf, case, on_failure):
    kwargs, kind, _, _ = FAILING[case]
    lay = SolveLayer(prob, KSPOptions(**kwargs, on_failure=on_failure))
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            try:
                u = lay(f=torch.ones(2, nf, dtype=F64), kappa=kappa_values(prob, kind))
            except SolverFailedError:
                assert on_failure == "raise"
                return
        assert on_failure == "warn"
        runtime = [w for w in caught if issubclass(w.category, RuntimeWarning)]
        if lay.stats.solves_by_engine.get("batched"):
            # One warning for the batch, naming how many samples failed.
            assert len(runtime) == 1 and "of 2 samples" in str(runtime[0].message)
        else:
            assert len(runtime) == 2  # one per failed sample, whether or not the iterate is finite
        assert lay.stats.failures == 2
        assert u.shape == (2, prob.output_size)
    finally:
        lay.close()


@pytest.mark.parametrize("case", ["nan", "unconverged"])
def test_failure_counted_per_sample_and_other_samples_intact(prob, nf, case):
    kwargs, kind, match, _ = FAILING[case]
    good = torch.ones(prob.control_size("kappa"), dtype=F64)
    if case == "nan":
        # Richardson step 10 is stable for kappa small enough: scale kappa down.
        good = 0.01 * good
    kappa = torch.stack([good, kappa_values(prob, kind), good])
    f = torch.ones(3, nf, dtype=F64)
    lay = SolveLayer(prob, KSPOptions(**kwargs))
    try:
        with pytest.raises(SolverFailedError, match=match):
            lay(f=f, kappa=kappa)
        assert lay.stats.forward_solves == 2  # sample 0 solved, sample 1 failed, sample 2 not reached
        assert lay.stats.failures == 1
    finally:
        lay.close()
    lay = SolveLayer(prob, KSPOptions(**kwargs, on_failure="warn"))
    try:
        with pytest.warns(RuntimeWarning, match=match):
            u = lay(f=f, kappa=kappa)
        assert lay.stats.forward_solves == 3
        assert lay.stats.failures == 1
        assert torch.isfinite(u[0]).all() and torch.isfinite(u[2]).all()
        torch.testing.assert_close(u[0], u[2], rtol=0, atol=0)
        if case == "unconverged":  # the good samples converged to rtol 1e-10
            ref = reference_solution(prob, f[0], good)
            torch.testing.assert_close(u[0], ref, rtol=0, atol=1e-8)
    finally:
        lay.close()


@pytest.mark.parametrize("on_failure", ["raise", "warn"])
def test_failure_in_adjoint_solve(prob, nf, nk, on_failure):
    bad, _, _, _ = FAILING["nan"]
    opts = KSPOptions.preset("lu", adjoint=KSPOptions(**bad, on_failure=on_failure))
    lay = SolveLayer(prob, opts)
    try:
        kappa = torch.ones(nk, dtype=F64, requires_grad=True)
        f = torch.ones(2, nf, dtype=F64, requires_grad=True)
        u = lay(f=f, kappa=kappa)
        assert torch.isfinite(u).all()
        assert lay.stats.failures == 0
        match = r"richardson\+none transposed solve produced NaN or inf"
        if on_failure == "raise":
            with pytest.raises(SolverFailedError, match=match):
                u.sum().backward()
            assert lay.stats.failures == 1
            assert lay.stats.backward_solves == 1
            assert kappa.grad is None and f.grad is None
        else:
            with pytest.warns(RuntimeWarning, match=match):
                u.sum().backward()
            assert lay.stats.failures == 2
            assert lay.stats.backward_solves == 2
            assert not torch.isfinite(f.grad).all()
    finally:
        lay.close()


def test_controls_restored_after_failure(prob, nf, nk):
    """The problem's control Functions keep the values they had before the failed call."""
    f_fn, k_fn = prob.control("f"), prob.control("kappa")
    f_before = np.linspace(0.5, 1.5, f_fn.x.array.size)
    k_before = np.linspace(2.0, 3.0, k_fn.x.array.size)
    f_fn.x.array[:] = f_before
    k_fn.x.array[:] = k_before
    try:
        for on_failure in ("raise", "warn"):
            kwargs, kind, match, _ = FAILING["indefinite"]
            lay = SolveLayer(prob, KSPOptions(**kwargs, on_failure=on_failure))
            try:
                f = torch.full((2, nf), 7.0, dtype=F64)
                kappa = kappa_values(prob, kind).expand(2, nk)
                if on_failure == "raise":
                    with pytest.raises(SolverFailedError, match=match):
                        lay(f=f, kappa=kappa)
                else:
                    with pytest.warns(RuntimeWarning, match=match):
                        lay(f=f, kappa=kappa)
            finally:
                lay.close()
            np.testing.assert_array_equal(f_fn.x.array, f_before)
            np.testing.assert_array_equal(k_fn.x.array, k_before)
    finally:
        f_fn.x.array[:] = 1.0
        k_fn.x.array[:] = 1.0


def test_layer_works_after_failure(prob, nf, nk):
    kwargs, kind, match, _ = FAILING["indefinite_pc"]
    lay = SolveLayer(prob, KSPOptions(**kwargs))
    try:
        f = torch.ones(nf, dtype=F64)
        with pytest.raises(SolverFailedError, match=match):
            lay(f=f, kappa=kappa_values(prob, kind))
        kappa = torch.linspace(1.0, 2.0, nk, dtype=F64)
        u = lay(f=f, kappa=kappa)
        torch.testing.assert_close(u, reference_solution(prob, f, kappa), rtol=0, atol=1e-8)
        assert lay.stats.failures == 1
        assert lay.stats.last.ok and lay.stats.last.reason_name == "CONVERGED_RTOL"
    finally:
        lay.close()


def test_layer_works_after_failure_without_matrix_control(prob, nf):
    """A failed call with kappa must not leave its matrix behind for a later call without kappa."""
    kwargs, kind, match, _ = FAILING["indefinite_pc"]
    lay = SolveLayer(prob, KSPOptions(**kwargs))
    try:
        f = torch.ones(nf, dtype=F64)
        before = lay(f=f)  # assembles A with the problem's kappa (= 1)
        with pytest.raises(SolverFailedError, match=match):
            lay(f=f, kappa=kappa_values(prob, kind))
        after = lay(f=f)  # must again use the problem's kappa
        torch.testing.assert_close(after, before, rtol=0, atol=1e-12)
    finally:
        lay.close()


@pytest.mark.parametrize("shared", [True, False])
def test_matrix_reassembled_after_call_with_matrix_control(prob, nf, nk, shared):
    """Regression: layer(f) after layer(f, kappa=2) solved with the stale kappa=2 matrix."""
    lay = SolveLayer(prob, "lu")
    try:
        f = torch.ones(nf, dtype=F64)
        u1 = lay(f=f)
        if shared:
            u2 = lay(f=f, kappa=torch.full((nk,), 2.0, dtype=F64))
        else:
            u2 = lay(f=f.expand(2, nf), kappa=torch.full((2, nk), 2.0, dtype=F64))[1]
        torch.testing.assert_close(u2, u1 / 2, rtol=0, atol=1e-12)
        u3 = lay(f=f)
        torch.testing.assert_close(u3, u1, rtol=0, atol=1e-12)
    finally:
        lay.close()


def test_lu_failure_message_does_not_recommend_lu():
    """A direct solve that produced NaN/inf points at the operator, not at the LU it already is. (A
    zero coefficient no longer gets this far: the assembled matrix is refused first.)"""
    from fempdl.solve.stats import SolveStats, report_failure
    stats = SolveStats(iterations=1, reason=4, reason_name="CONVERGED_ITS", residual_norm=None, time=0.0,
                       capped=False, ok=False)
    with pytest.raises(SolverFailedError, match=r"preonly\+lu solve produced NaN or inf; the factorisation met a "
                                                r"zero pivot: the matrix is singular \(a zero coefficient") as info:
        report_failure(KSPOptions.preset("lu"), stats, False, False)
    assert "preset('lu')" not in str(info.value)


def test_failure_warning_points_at_caller(prob, nf):
    kwargs, kind, match, _ = FAILING["nan"]
    lay = SolveLayer(prob, KSPOptions(**kwargs, on_failure="warn"))
    try:
        with pytest.warns(RuntimeWarning, match=match) as record:
            lay(f=torch.ones(nf, dtype=F64), kappa=kappa_values(prob, kind))
        assert record[0].filename == __file__
    finally:
        lay.close()


def test_nan_incoming_gradient_is_named(prob, nf):
    lay = SolveLayer(prob, KSPOptions(max_it=5))
    try:
        f = torch.ones(nf, dtype=F64, requires_grad=True)
        u = lay(f=f)
        with pytest.raises(ValueError, match=r"gradient.*NaN"):
            u.backward(torch.full_like(u, float("nan")))
    finally:
        lay.close()


def test_float32_overflow_not_silent(prob, nf, nk):
    lay = SolveLayer(prob, KSPOptions(max_it=50))
    try:
        with warnings.catch_warnings(record=True):
            warnings.simplefilter("always")
            with pytest.raises(OverflowError, match="overflows torch.float32; pass float64 controls"):
                lay(f=torch.full((nf,), 1e10), kappa=torch.full((nk,), 1e-30))
    finally:
        lay.close()


def test_closed_layer_repr(prob):
    lay = SolveLayer(prob, KSPOptions(max_it=5))
    lay.close()
    assert repr(lay) == "SolveLayer(closed)"


def test_problem_constants_are_declared_and_a_change_reaches_the_next_solve(msh):
    """A heat step declares dt through Problem(constants=...); halving dt changes u1 = (M + dt K)^-1 M u0
    exactly as a problem built with the halved dt does."""
    prob = forms.heat.problem(msh, controls=("u0",), dt=0.02)
    # The fixed number kappa is a Constant of the problem too.
    assert set(prob.constants) == {"dt", "kappa"} and float(prob.constants["dt"].value) == 0.02
    with pytest.raises(TypeError):
        prob.constants["dt"] = None                         # a read-only view: declared once, by the form
    u0 = torch.as_tensor(prob.interpolate(lambda x: np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])))
    layer = SolveLayer(prob, "lu")
    before = layer(u0=u0)
    prob.constants["dt"].value = 0.01
    after = layer(u0=u0)
    fresh = SolveLayer(forms.heat.problem(msh, controls=("u0",), dt=0.01), "lu")(u0=u0)
    assert torch.allclose(after, fresh, rtol=0, atol=1e-12)
    assert (after - before).abs().max() > 1e-4


def test_problem_constants_must_be_dolfinx_constants(raw):
    with pytest.raises(TypeError,
                       match=r"constants\['dt'\] must be a dolfinx.fem.Constant under a str name, got float"):
        Problem(raw["a"], raw["L"], (), controls={"f": raw["f"]}, constants={"dt": 0.1})
    assert not Problem(raw["a"], raw["L"], (), controls={"f": raw["f"]}).enclosed
