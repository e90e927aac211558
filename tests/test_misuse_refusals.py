"""What a user may hand PRDP, K_eps, k0, reference physics and the observation operators by mistake, and
what a saved state or a problem may be given after the fact: each is found and used, or refused in one
line that says what to pass; never a cap of 1 measured on nothing, a torch error, or a silent truncation."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl import Rollout, SolveLayer, forms, mesh
from fempdl.layer.observation import PointObservation
from fempdl.layer.reference import reference_physics
from fempdl.methods import k_eps as k_eps_module
from fempdl.methods.k_start import k_start
from fempdl.prdp import PRDP, k_eps
from fempdl.solve.stats import SolverFailedError

F64 = torch.float64


@pytest.fixture(scope="module")
def heat():
    return forms.heat.problem(mesh.load("lshape", h=0.3), controls=("u0",))


def capped(problem, k):
    """A Richardson + Jacobi layer capped at k sweeps."""
    layer = SolveLayer(problem, "jacobi")
    layer.max_it = k
    return layer


class Model(torch.nn.Module):
    def __init__(self, layer):
        super().__init__()
        self.net, self.layer = torch.nn.Linear(3, 3), layer


def test_prdp_finds_the_layers_inside_a_module_and_says_what_to_pass_otherwise(heat):
    layer = capped(heat, 7)
    PRDP(torch.nn.Sequential(torch.nn.Linear(3, 3), layer), k0=2, k_cap=10)
    assert layer.max_it == 2
    PRDP(Model(layer), k0=3, k_cap=10)
    assert layer.max_it == 3
    rollout = Rollout(layer)                  # the outermost: the rollout, not its step layer a second time
    PRDP(torch.nn.ModuleList([rollout]), k0=4, k_cap=10)
    assert layer.max_it == 4
    with pytest.raises(TypeError, match=r"not a mapping; pass its values: PRDP\(list\(targets.values\(\)\)"):
        PRDP({"a": layer}, k0=2, k_cap=10)
    with pytest.raises(TypeError, match="the Sequential passed as a target holds no solve layer or rollout"):
        PRDP(torch.nn.Sequential(torch.nn.Linear(3, 3)), k0=2, k_cap=10)


def test_reference_physics_routes_a_rollout_and_a_module_and_names_a_bad_list_item(heat):
    layer = capped(heat, 2)
    u0 = torch.ones(heat.output_size, dtype=F64)
    with torch.no_grad():
        exact = SolveLayer(heat, "lu")(u0=u0)
        for target in (Rollout(layer), Model(layer), [layer]):
            with reference_physics(target):
                assert torch.allclose(layer(u0=u0), exact, rtol=1e-10, atol=1e-12)
        assert not torch.allclose(layer(u0=u0), exact, rtol=1e-6, atol=0.0)
    with pytest.raises(TypeError, match="the layers must be a SolveLayer.*got list whose item 1 is a str"):
        with reference_physics([layer, "x"]):
            pass


def test_a_saved_state_with_a_k_prdp_could_not_have_saved_is_refused(heat):
    layer = capped(heat, 2)
    ctrl = PRDP(layer, k0=2, k_cap=10)
    state = ctrl.state_dict()
    with pytest.raises(ValueError, match=r"saved PRDP state's k \(1000000\) is above its k_cap \(10\)"):
        ctrl.load_state_dict({**state, "k": 10 ** 6})
    for bad in ("5", 2.7):
        with pytest.raises(TypeError, match="a saved PRDP state's k must be an int"):
            ctrl.load_state_dict({**state, "k": bad})
    assert layer.max_it == 2
    ctrl.load_state_dict({**state, "k": np.int64(6)})
    assert ctrl.k == layer.max_it == 6 and type(ctrl.k) is int


def test_a_validation_of_more_than_one_number_is_refused_in_one_line(heat):
    ctrl = PRDP(capped(heat, 2), k0=2, k_cap=10, judge="capped")
    for metric in (torch.tensor([1.0, 2.0]), np.array([1.0, 2.0])):
        with pytest.raises(ValueError, match=r"metric must be one number, got a \w+ of shape \(2,\): reduce it"):
            ctrl.step(metric)
    ctrl.step(torch.tensor(0.5))
    ctrl.step(np.float32(0.4))
    assert [rec.metric for rec in ctrl.history] == [0.5, pytest.approx(0.4)]


@pytest.mark.parametrize("measure", [k_eps, k_start])
def test_a_call_that_never_reaches_the_target_is_refused(heat, measure):
    layer, other = capped(heat, 2), capped(heat, 2)
    u0 = torch.ones(heat.output_size, dtype=F64)
    assert k_eps(layer, u0=u0) > 1
    for call in (lambda: None, lambda: other(u0=u0)):
        with pytest.raises(ValueError, match="the call did not solve with the target: none of its 1 layer"):
            measure(layer, call=call)


def test_k_start_refuses_a_call_that_returns_no_tensor(heat):
    layer = capped(heat, 2)
    u0 = torch.ones(heat.output_size, dtype=F64)
    with pytest.raises(TypeError, match="call must return the tensor .* to compare, got float"):
        k_start(layer, call=lambda: float(layer(u0=u0).sum()))


def test_a_failed_k_eps_measurement_inside_step_names_the_measurement(heat, monkeypatch):
    layer = capped(heat, 1)
    u0 = torch.ones(heat.output_size, dtype=F64)
    with torch.no_grad():
        data = SolveLayer(heat, "lu")(u0=u0)

    def validate():                              # capped at 1 sweep it is far from its reference: the gap opens
        return float(((layer(u0=u0) - data) ** 2).sum() / (data ** 2).sum()) + 1e-9

    def diverging(*args, **kwargs):
        raise SolverFailedError("KSP (richardson) diverged: DIVERGED_DTOL", None)
    ctrl = PRDP(layer, k0=1, k_cap=None)
    monkeypatch.setattr(k_eps_module, "k_eps", diverging)
    with pytest.raises(SolverFailedError, match=r"PRDP measured K_eps again at step \d+ .* a solve failed: KSP "
                                                r"\(richardson\) diverged.*remeasure=False"):
        ctrl.step(validate)


def test_point_observation_refuses_an_integer_field(heat):
    observe = PointObservation(heat, np.array([[0.25, 0.25]]))
    u = torch.arange(heat.output_size)
    with pytest.raises(TypeError, match=r"u has dtype torch.int64; use float32 or float64 \(e.g. u.double\(\)\)"):
        observe(u)
    assert observe(u.double()).dtype == F64


def test_what_a_problem_is_built_from_is_fixed_and_a_fixed_coefficient_keeps_its_bounds(heat):
    problem = forms.poisson.problem(mesh.load("lshape", h=0.3))
    layer = SolveLayer(problem, "lu")
    for name, value in (("bcs", ()), ("a", problem.a), ("L", problem.L)):
        with pytest.raises(AttributeError, match=f"problem.{name} is fixed when the problem is built"):
            setattr(problem, name, value)
    f = torch.ones(problem.control_size("f"), dtype=F64)
    problem.constants["kappa"].value = 2.0       # a fixed number is one of the problem's Constants
    u2 = layer(f=f)
    problem.constants["kappa"].value = -1.0
    with pytest.raises(ValueError, match=r"Constant 'kappa' must be > 0 \(problem.positive\), got -1"):
        layer(f=f)
    problem.constants["kappa"].value = 1.0
    assert torch.allclose(layer(f=f), 2.0 * u2, rtol=1e-10)


def test_a_resumed_controller_measures_the_calls_the_uninterrupted_one_measures(heat):
    # The health check measures the first training call at new caps and every 8th after; a resumed run
    # that measured its first call again would refine where the uninterrupted run does not.
    u0 = torch.ones(heat.output_size, dtype=F64)
    layer = capped(heat, 3)
    ctrl = PRDP(layer, k0=3, k_cap=50)
    for _ in range(3):
        layer(u0=u0.clone().requires_grad_()).sum().backward()
    saved = ctrl.state_dict()
    resumed_layer = capped(heat, 3)
    resumed = PRDP(resumed_layer, k0=3, k_cap=50)
    assert resumed_layer.health_schedule != layer.health_schedule
    resumed.load_state_dict(saved)
    assert resumed_layer.health_schedule == layer.health_schedule
