"""PRDP judged with the physics a model is deployed with: reference physics, the gap rule, K_eps measured
again, the capped-validation warning, and K_eps / k_start / preflight on everything PRDP moves."""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, SolveLayer, forms, mesh
from fempdl.ksp_adjoint import KSPOptions
from fempdl.prdp import PRDP, PRDPValidationWarning, k_eps, k_start, preflight, reference_physics


@pytest.fixture(scope="module")
def msh():
    return mesh.load("lshape", h=0.2)


@pytest.fixture(scope="module")
def heat(msh):
    return forms.heat.problem(msh, controls=("u0", "f"), dt=0.05)


def fields(problem, count, seed=0):
    x = torch.from_numpy(problem.dof_coordinates()[:, :2])
    g = torch.Generator().manual_seed(seed)
    a = torch.randn(count, 4, dtype=torch.float64, generator=g)
    modes = torch.stack([torch.sin(x[:, 0] + 1), torch.cos(2 * x[:, 1]), x[:, 0] * x[:, 1], torch.exp(x[:, 0])], 1)
    return a @ modes.T


def jacobi(problem, k=2):
    return SolveLayer(problem, KSPOptions.preset("jacobi", max_it=k))


def test_reference_physics_solves_converged_and_counts_apart(heat):
    layer, exact = jacobi(heat), SolveLayer(heat, "lu")
    u0 = fields(heat, 3)
    with torch.no_grad():
        capped, truth = layer(u0=u0), exact(u0=u0)
        with reference_physics(layer):
            judged = layer(u0=u0)
        after = layer(u0=u0)
    assert torch.allclose(judged, truth, rtol=0, atol=1e-12 * truth.abs().max())
    assert (capped - truth).norm() > 1e-3 * truth.norm()           # the cap is visible outside
    assert torch.equal(after, capped)
    assert layer.stats.forward_solves == 6 and layer.reference_stats.forward_solves == 3
    assert "route" not in dict(layer.named_modules()) and set(layer.state_dict()) == {"_extra_state"}


def test_a_gradient_taken_at_reference_physics_is_the_converged_one_after_the_block(heat):
    layer, exact = jacobi(heat), SolveLayer(heat, "lu")
    u0 = fields(heat, 2).requires_grad_()
    target = fields(heat, 2, seed=1)
    with reference_physics(layer):
        loss = (layer(u0=u0) - target).square().sum()
    (grad,) = torch.autograd.grad(loss, u0)                      # the backward runs after the block
    (expected,) = torch.autograd.grad((exact(u0=u0) - target).square().sum(), u0)
    assert torch.allclose(grad, expected, rtol=1e-10, atol=1e-14)


def leaning_validation(layer, problem, k_lean=2):
    """A validation whose model reproduces the data only through a solver capped at ``k_lean``: its capped
    metric is tiny at that cap, its metric at reference physics is not."""
    u0 = fields(problem, 4)
    with torch.no_grad():
        data = jacobi(problem, k_lean)(u0=u0)

    def validate():
        return float(((layer(u0=u0) - data) ** 2).sum() / (data ** 2).sum()) + 1e-6
    return validate, u0


def test_at_k_cap_an_open_gap_measures_k_eps_again_and_raises_k_cap(heat):
    layer = jacobi(heat)
    validate, u0 = leaning_validation(layer, heat)
    ctrl = PRDP(layer, k0=3, k_cap=3, delta=2, k_eps_rtol=1e-6)
    for _ in range(3):
        ctrl.step(validate)
    measured = k_eps(layer, u0=u0, rtol=1e-6)
    assert ctrl.k_cap == measured > 3 and layer.max_it > 3
    assert [rec.cause for rec in ctrl.history if rec.refined] == ["k_eps"]
    assert ctrl.history[-1].k_cap == measured
    state = ctrl.state_dict()
    again = PRDP(jacobi(heat), k0=3, k_cap=3, delta=2, k_eps_rtol=1e-6)
    again.load_state_dict(state)
    assert again.k_cap == measured and again.k == ctrl.k
    old = {key: value for key, value in state.items() if key != "k_cap"}     # saved before k_cap moved
    old["settings"] = {k: v for k, v in state["settings"].items() if k not in ("judge", "gap", "remeasure")}
    again.load_state_dict(old)
    assert again.k_cap == 3


def test_a_capped_validation_passed_as_a_number_warns_once(heat):
    layer = jacobi(heat)
    u0 = fields(heat, 2)
    ctrl = PRDP(layer, k0=2)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with torch.no_grad(), ctrl.reference():
            layer(u0=u0)
        ctrl.step(1.0)                                  # validated at reference physics: no warning
        layer(u0=u0.requires_grad_()).sum().backward()    # training calls: no warning
        ctrl.step(1.0)
    with torch.no_grad():
        layer(u0=u0)
    with pytest.warns(PRDPValidationWarning, match=r"ctrl.step\(validate\)"):
        ctrl.step(1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with torch.no_grad():
            layer(u0=u0)
        ctrl.step(1.0)                                  # once
        capped = PRDP(layer, k0=2, judge="capped")
        with torch.no_grad():
            layer(u0=u0)
        capped.step(1.0)                                # a model deployed capped: validated as it should be


def test_settings_and_step_errors(heat):
    with pytest.raises(ValueError, match="judge must be one of"):
        PRDP(None, judge="converged")
    with pytest.raises(ValueError, match="gap must be a finite relative difference > 0"):
        PRDP(None, gap=0.0)
    with pytest.raises(TypeError, match="moves no solve layers"):
        PRDP(None).step(lambda: 1.0)
    with pytest.raises(TypeError, match=r"metric must be a number \(or a function returning one\), got str"):
        PRDP(jacobi(heat)).step(lambda: "small")


def test_k_eps_takes_the_batch_from_the_batched_input_in_any_order(heat):
    layer = jacobi(heat)
    u0 = fields(heat, 3)
    f = fields(heat, 1, seed=3)[0]                               # shared by the batch
    each = [k_eps(layer, u0=u0[i], f=f, rtol=1e-6) for i in range(3)]
    u0 = u0[torch.tensor(each).argsort()]                        # sample 0 needs the fewest
    each = sorted(each)
    assert each[0] < each[-1]                                    # so sample 0 alone is not K_eps
    assert k_eps(layer, f=f, u0=u0, rtol=1e-6) == k_eps(layer, u0=u0, f=f, rtol=1e-6) == max(each)
    assert k_eps(layer, f=f, u0=u0, rtol=1e-6, batch=2) == max(each)


def test_k_eps_k_start_and_preflight_on_a_rollout(heat):
    step = jacobi(heat, 3)
    rollout = Rollout(step, "u0")
    initial, f = fields(heat, 2), fields(heat, 1, seed=2)[0]
    run = dict(initial=initial, steps=3, f=f)
    with torch.no_grad():
        states = Rollout(SolveLayer(heat, "lu"), "u0")(**run)         # (2, 4, n)
    per_step = [k_eps(step, u0=states[:, k], f=f, initial_guess=states[:, k], rtol=1e-8) for k in range(3)]
    assert k_eps(rollout, rtol=1e-8, **run) == max(per_step)
    assert step.max_it == 3 and step.stats.forward_solves == 0

    k0 = k_start(rollout, tolerance=0.05, **run)

    def error(k):
        step.max_it = k
        with torch.no_grad():
            out = rollout(**run)
        return float(((out - states).norm(dim=-1) / states.norm(dim=-1)).nan_to_num(0.0).max())
    assert error(k0) <= 0.05 < error(k0 - 1)
    step.max_it = 3

    net = torch.nn.Linear(1, 1).double()

    def train_step():
        (rollout(initial=initial * net.weight.squeeze(), steps=3, f=f) ** 2).mean().backward()
    report = preflight(train_step, rollout, call=lambda: rollout(**run))    # its `steps` is preflight's own
    assert report.k_cap == k_eps(rollout, **run) and 1 <= report.k0 <= report.k_cap
    assert step.max_it == 3


def test_k_eps_of_a_list_of_layers_is_the_largest(heat, msh):
    first, second = jacobi(heat), jacobi(forms.heat.problem(msh, controls=("u0",), dt=0.5))
    a, b = fields(heat, 2), fields(heat, 2, seed=4)
    both = k_eps([first, second], call=lambda: (first(u0=a), second(u0=b)))
    assert both == max(k_eps(first, u0=a), k_eps(second, u0=b))
    with pytest.raises(TypeError, match="give call= a function"):
        k_eps([first, second], u0=a)


def test_a_newton_rollouts_k_eps_is_its_most_newton_steps(msh):
    problem = forms.nonlinear_diffusion.problem(msh, controls=("u0",), alpha=5.0, dt=0.05)
    step = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"))
    initial = 0.5 * fields(problem, 2)
    reference = NonlinearSolveLayer(problem, NewtonOptions(ksp="lu", rtol=1e-8))
    with torch.no_grad():
        states = Rollout(reference, "u0")(initial, 4)
    reference.stats.reset()
    with torch.no_grad():
        for k in range(4):
            reference(u0=states[:, k], initial_guess=states[:, k])
    assert k_eps(Rollout(step, "u0"), initial=initial, steps=4, rtol=1e-8) == reference.stats.max_newton_steps > 1
    assert np.isfinite(float(states.norm()))


def test_k0s_default_tolerance_follows_what_the_capped_gradient_is(heat, msh):
    from fempdl.methods.k_start import CONSISTENT_TOLERANCE, IMPLICIT_TOLERANCE, default_tolerance
    nonlinear = forms.nonlinear_diffusion.problem(msh, controls=("f",), alpha=2.0)
    assert default_tolerance([jacobi(heat)]) == CONSISTENT_TOLERANCE == 0.5
    assert default_tolerance([SolveLayer(heat, KSPOptions.preset("cg", max_it=3), diff="unrolled")]) == 0.5
    assert default_tolerance([SolveLayer(heat, KSPOptions.preset("cg", max_it=3))]) == IMPLICIT_TOLERANCE == 0.01
    assert default_tolerance([jacobi(forms.heat.problem(msh, controls=("u0", "kappa")))]) == 0.01
    assert default_tolerance([NonlinearSolveLayer(nonlinear, NewtonOptions(max_it=2, ksp="lu"))]) == 0.01
    assert default_tolerance([NonlinearSolveLayer(nonlinear, NewtonOptions(max_it=2, ksp="lu"),
                                                  diff="unrolled")]) == 0.5
    layer = SolveLayer(heat, KSPOptions.preset("cg", max_it=3))
    u0 = fields(heat, 2)
    assert k_start(layer, u0=u0) == k_start(layer, tolerance=0.01, u0=u0) > k_start(layer, tolerance=0.5, u0=u0)
