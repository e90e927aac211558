"""preflight: k0, K_eps and the solver's share of a user's own training step, and what PRDP can save there."""
from __future__ import annotations

import pytest
import torch

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms
from fempdl.methods.preflight import Preflight, preflight
from fempdl.prdp import k_eps, k_start


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
    assert calls == [report.k_cap] * 3 and layer.max_it == 3          # run at K_eps, the cap put back
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
    assert pays.summary().endswith("PRDP can save at most 76% of the wall time; use PRDP(..., k0=2, k_cap=40)")
    idle = Preflight(k0=2, k_cap=4, step_time=0.010, capped_time=0.001, capped_parts=("iterations",), cost_ratio=0.5)
    assert not idle.pays() and "PRDP can save at most 5% of the wall time, below 10%: PRDP cannot pay in this " \
                               "loop; train at K_eps (max_it=4)" in idle.summary()


def test_preflight_errors(coarse_lshape):
    layer = SolveLayer(forms.poisson.problem(coarse_lshape, controls=("f",)), KSPOptions.preset("jacobi", max_it=3))
    f = torch.ones(layer.problem.control_size("f"), dtype=torch.float64)
    with pytest.raises(TypeError, match="step must be a callable"):
        preflight(None, layer, f=f)
    with pytest.raises(ValueError, match="steps"):
        preflight(lambda: None, layer, steps=0, f=f)
    with pytest.raises(TypeError, match="target must be a SolveLayer"):
        preflight(lambda: None, object(), f=f)
