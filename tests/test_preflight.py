"""preflight: k0, K_eps and the solver's share of a user's own training step, and what PRDP can save there."""
from __future__ import annotations

import re

import pytest
import torch

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms, mesh
from fempdl.methods.preflight import Preflight, preflight
from fempdl.prdp import PRDP, PRDPSettings, k_eps, k_start


def test_preflight_of_a_hand_written_loop(coarse_lshape):
    prob = forms.poisson.problem(coarse_lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=3))
    n = prob.control_size("f")
    torch.manual_seed(0)
    z = torch.randn(8, 4, dtype=torch.float64)
    net = torch.nn.Linear(4, n).double()
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    with torch.no_grad():
        target = SolveLayer(prob, "lu")(f=z @ torch.randn(4, n, dtype=torch.float64))
    calls = []

    def step():
        opt.zero_grad()
        ((layer(f=net(z)) - target) ** 2).sum().backward()
        opt.step()
        calls.append(layer.max_it)

    with torch.no_grad():
        f = net(z)
    report = preflight(step, layer, steps=2, f=f)
    assert report.k_cap == k_eps(layer, f=f) and report.k0 == k_start(layer, f=f)
    # One step at k0 (its health checked), the others at K_eps; the cap put back.
    assert calls == [report.k0] + [report.k_cap] * 3 and layer.max_it == 3 and report.forward_k0 == report.k0
    assert 0.0 < report.solver_share <= 1.0 and report.capped_parts == ("iterations",)
    # A pure cap runs exactly K iterations: solves at k0 cost k0 / K_eps of those at K_eps.
    assert report.cost_ratio == pytest.approx(report.k0 / report.k_cap)
    assert report.max_saving == pytest.approx(report.solver_share * (1 - report.k0 / report.k_cap))


def test_preflight_of_a_newton_loop_counts_assembly(coarse_lshape):
    prob = forms.nonlinear_diffusion.problem(coarse_lshape, controls=("f",), alpha=5.0)
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
    f = torch.full((prob.control_size("f"),), 5.0, dtype=torch.float64, requires_grad=True)
    report = preflight(lambda: layer(f=f).sum().backward(), layer, steps=1, f=f.detach())
    assert report.capped_parts == ("iterations", "setup", "assembly")
    assert report.k_cap >= report.k0 >= 1 and layer.max_it == 1
    # From a warm start at the solution a Newton cap is a budget both caps leave unused: nothing to save.
    with torch.no_grad():
        solution = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))(f=f)
    warm = preflight(lambda: layer(f=f, initial_guess=solution).sum().backward(), layer, steps=1, f=f.detach(),
                     initial_guess=solution)
    assert warm.cost_ratio == 1.0 and warm.max_saving == 0.0 and not warm.pays()


def test_the_verdict_names_the_caps_or_says_prdp_cannot_pay():
    pays = Preflight(k0=2, k_cap=40, step_time=0.010, capped_time=0.008, capped_parts=("iterations",), cost_ratio=0.05)
    assert pays.max_saving == pytest.approx(0.8 * 0.95)
    assert "PRDP can save at most 76% of the wall time; use ctrl = PRDP(target, k0=2, k_cap=40) " \
           "(report.prdp(target)), its other settings PRDP's defaults, among them growth=1.5, gap=0.05, " \
           "judge='reference'; call ctrl.step(validate) after every epoch" in pays.summary()
    assert pays.summary().endswith("and ctrl.finish(validate) after the last")
    idle = Preflight(k0=2, k_cap=4, step_time=0.010, capped_time=0.001, capped_parts=("iterations",), cost_ratio=0.5)
    assert not idle.pays() and "PRDP can save at most 5% of the wall time, below 10%: PRDP cannot pay in this " \
                               "loop; train at K_eps (max_it=4) or with converged solves: ctrl = PRDP(target, " \
                               "k0=4, k_cap=4) (report.prdp(target)) keeps the loop there" in idle.summary()
    assert idle.advice() == {"k0": 4, "k_cap": 4} and pays.advice() == {"k0": 2, "k_cap": 40}


@pytest.mark.parametrize("report", [
    Preflight(k0=3, k_cap=60, step_time=0.01, capped_time=0.009, capped_parts=("iterations",), cost_ratio=0.05),
    Preflight(k0=3, k_cap=5, step_time=0.01, capped_time=0.0001, capped_parts=("iterations",), cost_ratio=0.6)])
def test_the_printed_advice_executed_builds_the_prdp_the_docs_describe(coarse_lshape, report):
    layer = SolveLayer(forms.poisson.problem(coarse_lshape, controls=("f",)), KSPOptions.preset("jacobi", max_it=1))
    printed = re.search(r"ctrl = (PRDP\(target, [^)]*\))", report.summary()).group(1)
    ctrl = eval(printed, {"PRDP": PRDP, "target": layer})          # what a user who copies it runs
    built = report.prdp(layer)
    expected = PRDPSettings(k0=report.k0 if report.pays() else report.k_cap, k_cap=report.k_cap)
    assert ctrl.settings == built.settings == expected and layer.max_it == expected.k0
    # Every default the advice names is the controller's.
    named = dict(re.findall(r"(growth|gap|judge)=([^,;]+)", report.summary()))
    assert {k: str(getattr(ctrl.settings, k)) if k != "judge" else repr(ctrl.settings.judge) for k in named} == named


def test_preflight_errors(coarse_lshape):
    layer = SolveLayer(forms.poisson.problem(coarse_lshape, controls=("f",)), KSPOptions.preset("jacobi", max_it=3))
    f = torch.ones(layer.problem.control_size("f"), dtype=torch.float64)
    with pytest.raises(TypeError, match="step must be a callable"):
        preflight(None, layer, f=f)
    with pytest.raises(ValueError, match="steps"):
        preflight(lambda: None, layer, steps=0, f=f)
    with pytest.raises(TypeError, match="target must be a SolveLayer"):
        preflight(lambda: None, object(), f=f)


def test_preflights_k0_is_raised_where_the_first_training_steps_adjoint_is_garbage():
    # Capped CG differentiated implicitly: the forward is within 1% at k_start's k0, but the adjoint of a
    # misfit at a few sensors is not within PRDP's adjoint limit (1%) there; preflight's k0 is the cap the
    # health check leaves after the loop's first step, and a PRDP built from it does not refine on the next.
    heat = forms.heat.problem(mesh.load("lshape", h=0.2), controls=("u0",), dt=0.05)
    x = torch.from_numpy(heat.dof_coordinates()[:, :2])
    modes = torch.stack([torch.sin(x[:, 0] + 1), torch.cos(2 * x[:, 1]), x[:, 0] * x[:, 1], torch.exp(x[:, 0])], 1)
    u0 = torch.randn(2, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) @ modes.T
    sensors = torch.zeros(2, heat.output_size, dtype=torch.float64)
    sensors[:, ::13] = 1.0                       # the loss's gradient: the adjoint's right-hand side
    torch.manual_seed(0)
    net = torch.nn.Linear(heat.output_size, heat.output_size).double()
    layer = SolveLayer(heat, KSPOptions.preset("cg", max_it=2))

    def step():
        (layer(u0=net(u0)) * sensors).sum().backward()
    report = preflight(step, layer, u0=u0)
    assert report.forward_k0 == k_start(layer, u0=u0) < report.k0 <= report.k_cap and layer.max_it == 2
    assert f"k0 {report.k0} (k_start's {report.forward_k0}, raised by the health check" in report.summary()
    ctrl = report.prdp(layer)
    step()
    assert not ctrl.health_refinements and layer.last_adjoint_health_ratio <= 0.01
