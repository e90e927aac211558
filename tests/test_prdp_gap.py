"""PRDP's gap at every step: the capped metric against the reference one, the search for the cap that
closes it, the closing call, and the health check of a training call's adjoint solves."""
from __future__ import annotations

import warnings

import pytest
import torch

from fempdl import SolveLayer, forms, mesh
from fempdl.ksp_adjoint import KSPOptions
from fempdl.methods.prdp_gap import closing_cap, relative_gap
from fempdl.prdp import PRDP, PRDPGapWarning


@pytest.fixture(scope="module")
def heat():
    return forms.heat.problem(mesh.load("lshape", h=0.2), controls=("u0", "f"), dt=0.05)


def fields(problem, count, seed=0):
    x = torch.from_numpy(problem.dof_coordinates()[:, :2])
    g = torch.Generator().manual_seed(seed)
    modes = torch.stack([torch.sin(x[:, 0] + 1), torch.cos(2 * x[:, 1]), x[:, 0] * x[:, 1], torch.exp(x[:, 0])], 1)
    return torch.randn(count, 4, dtype=torch.float64, generator=g) @ modes.T


def jacobi(problem, k):
    return SolveLayer(problem, KSPOptions.preset("jacobi", max_it=k))


def leaning(problem, layer, k_lean=2):
    """A validation whose model reproduces its data only through a solver capped at ``k_lean``: tiny at
    that cap, far larger at reference physics."""
    u0 = fields(problem, 4)
    with torch.no_grad():
        data = jacobi(problem, k_lean)(u0=u0)
    return lambda: float(((layer(u0=u0) - data) ** 2).sum() / (data ** 2).sum()) + 1e-6


def test_the_gap_acts_while_the_plateau_rule_refines():
    # The reference metric falls in stairs, so the plateau rule refines on its own (every third step, growth
    # 1.5); the capped one is 10x lower (a model leaning on the cap) until K reaches 40. The gap, known at
    # every step, doubles K at once instead of waiting for plateaus.
    for gap, expected in ((None, [2, 2, 2, 2, 2, 2, 3, 3, 3, 5, 5, 5]),
                          (0.05, [2, 4, 8, 16, 32, 40, 40, 40, 40, 40, 40, 40])):
        ctrl = PRDP(None, k0=2, k_cap=40, delta=3, ema_window=1, gap=gap)
        ks = []
        for i in range(12):
            ks.append(ctrl.k)
            metric = 0.7 ** (i // 3)
            ctrl.step(metric, capped=metric / 10 if ctrl.k < 40 else metric * 1.01)
        assert ks == expected
    assert [(rec.k, rec.cause) for rec in ctrl.history if rec.refined] == [(k, "gap") for k in (2, 4, 8, 16, 32)]
    assert all(rec.gap == pytest.approx(9.0) for rec in ctrl.history[:5])          # |0.1 - 1| / 0.1
    assert all(rec.gap == pytest.approx(0.01) and not rec.refined for rec in ctrl.history[5:])


def test_an_open_gap_moves_k_to_the_cap_that_closes_it(heat):
    layer = jacobi(heat, 2)
    validate = leaning(heat, layer)
    ctrl = PRDP(layer, k0=2, k_cap=60, remeasure=False)
    ctrl.step(validate)
    record = ctrl.history[0]
    with torch.no_grad(), ctrl.reference():
        reference = validate()

    def capped_at(k):
        layer.max_it = k
        with torch.no_grad():
            return validate()
    brute = {k: capped_at(k) for k in range(2, 61)}
    layer.max_it = ctrl.k
    assert record.metric == pytest.approx(reference, rel=1e-12) and record.gap > 1.0 and record.cause == "gap"
    # Doubling 4, 8, ... until closed, then bisection to within an eighth; each probe a real capped validation.
    ks = [k for k, _ in record.probes]
    assert ks[:2] == [4, 8] and all(value == pytest.approx(brute[k], rel=1e-12) for k, value in record.probes)
    closed = [k for k in ks if relative_gap(brute[k], reference) <= 0.05]
    open_ = [k for k in ks if relative_gap(brute[k], reference) > 0.05]
    assert ctrl.k == min(closed) and ctrl.k - max(k for k in open_ if k < ctrl.k) <= max(1, ctrl.k // 8)
    assert relative_gap(brute[ctrl.k], reference) <= 0.05 < relative_gap(brute[2], reference)
    # The gap is measured at every step, and the cap stays where the metric no longer moves it.
    ctrl.step(validate)
    assert ctrl.history[1].gap <= 0.05 and ctrl.history[1].capped_metric is not None and not ctrl.history[1].refined
    assert layer.max_it == ctrl.k


def test_the_search_is_bounded_and_says_when_it_cannot_close():
    calls = []

    def never(k):
        calls.append(k)
        return 0.1
    found = closing_cap(never, 1.0, 3, 20, 0.05)
    assert (found.k, found.closed) == (20, False) and calls == [6, 12, 20]
    assert closing_cap(lambda k: 1.0 if k >= 7 else 0.5, 1.0, 1, 100, 0.05).k == 7     # 2, 4, 8; 6; 7


def test_finish_closes_the_gap_or_warns_naming_both_metrics(heat):
    layer = jacobi(heat, 2)
    validate = leaning(heat, layer)
    ctrl = PRDP(layer, k0=2, k_cap=60, remeasure=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", PRDPGapWarning)
        done = ctrl.finish(validate)
    assert done.closed and done.gap <= 0.05 and done.k == ctrl.k == layer.max_it > 2 and not ctrl.history
    with torch.no_grad(), ctrl.reference():
        assert done.metric == pytest.approx(validate(), rel=1e-12)
    stuck = jacobi(heat, 2)
    ctrl = PRDP(stuck, k0=2, k_cap=3, remeasure=False)
    with pytest.warns(PRDPGapWarning, match=r"PRDP ends with the gap open: at K = 3 the validation metric is "
                                            r"\S+ with the capped solves and \S+ with converged ones"):
        done = ctrl.finish(leaning(heat, stuck))
    assert not done.closed and done.k == 3 and done.gap > 0.05
    judged = PRDP(jacobi(heat, 2), k0=2, judge="capped").finish(1.0)
    assert judged.closed and judged.gap is None and judged.metric == 1.0


def test_a_garbage_adjoint_refines_and_is_solved_again_at_the_refined_cap(heat):
    # A warm start at the solution makes the forward healthy (its residual is round-off); the adjoint starts
    # from zero, and two Jacobi sweeps do not shrink its residual 10-fold: the backward refines and solves again
    # (to the health limit alone: no adjoint limit, which a detached start is held to otherwise).
    u0, f = fields(heat, 2), fields(heat, 2, seed=5)
    with torch.no_grad():
        u = SolveLayer(heat, "lu")(u0=u0, f=f)
    weights = fields(heat, 2, seed=7)
    layer = jacobi(heat, 2)
    ctrl = PRDP(layer, k0=2, k_cap=200, health=0.1, growth=1.0, adjoint_health=None)
    f_in = f.clone().requires_grad_()
    (layer(u0=u0, f=f_in, initial_guess=u) * weights).sum().backward()
    assert layer.last_health_ratio == 0.0 and ctrl.k > 2
    assert [e["k"] for e in ctrl.health_refinements] == list(range(2, ctrl.k))
    assert layer.last_adjoint_health_ratio <= 0.1 < ctrl.health_refinements[-1]["ratio"]
    # The gradient is the implicit one with the refined cap's adjoint: that of a layer capped there.
    again = jacobi(heat, ctrl.k)
    f_ref = f.clone().requires_grad_()
    (again(u0=u0, f=f_ref, initial_guess=u) * weights).sum().backward()
    assert torch.allclose(f_in.grad, f_ref.grad, rtol=1e-12, atol=1e-15 * f_ref.grad.abs().max())


def test_an_implicit_gradients_adjoint_must_shrink_to_the_adjoint_limit(heat):
    # Two sweeps of either solver shrink the adjoint's residual, so Jacobi's exact K-step derivative keeps
    # them; capped CG's gradient is the implicit approximation, as wrong as its adjoint: it refines to 1%.
    u0, weights = fields(heat, 2), fields(heat, 2, seed=7)
    ks = {}
    for preset in ("jacobi", "cg"):
        layer = SolveLayer(heat, KSPOptions.preset(preset, max_it=2))
        ctrl = PRDP(layer, k0=2, k_cap=200, growth=1.0)
        (layer(u0=u0.clone().requires_grad_()) * weights).sum().backward()
        assert layer.last_health_ratio <= 1.0
        ks[preset] = ctrl.k
        if preset == "jacobi":
            assert 0.01 < layer.last_adjoint_health_ratio <= 1.0 and not ctrl.health_refinements
        else:
            assert layer.last_adjoint_health_ratio <= 0.01 < ctrl.health_refinements[-1]["ratio"]
            assert [e["k"] for e in ctrl.health_refinements] == list(range(2, ctrl.k))
    assert ks["jacobi"] == 2 < ks["cg"]
    off = SolveLayer(heat, KSPOptions.preset("cg", max_it=2))
    PRDP(off, k0=2, k_cap=200, adjoint_health=None)            # the health limit alone: a shrinking adjoint passes
    (off(u0=u0.clone().requires_grad_()) * weights).sum().backward()
    assert off.max_it == 2 and off.last_adjoint_health_ratio <= 1.0


def test_a_detached_warm_starts_adjoint_must_shrink_to_the_adjoint_limit(heat):
    # From a start at the solution the forward is exact at any cap, but a start that carries no gradient
    # leaves Jacobi's K-step derivative ((I - M^K) A^-1) short of the physics' A^-1 by the adjoint's
    # residual: held to 1% it refines; with the start differentiated the derivative is the map's, kept at 2.
    u0, f, weights = fields(heat, 2), fields(heat, 2, seed=5), fields(heat, 2, seed=7)
    with torch.no_grad():
        u = SolveLayer(heat, "lu")(u0=u0, f=f)
    f_exact = f.clone().requires_grad_()
    (SolveLayer(heat, "lu")(u0=u0, f=f_exact) * weights).sum().backward()
    for detached in (True, False):
        layer = jacobi(heat, 2)
        ctrl = PRDP(layer, k0=2, k_cap=200, growth=1.0)
        f_in, start = f.clone().requires_grad_(), u.clone().requires_grad_(not detached)
        (layer(u0=u0, f=f_in, initial_guess=start) * weights).sum().backward()
        assert layer.last_health_ratio <= 1.0                  # the forward (round-off from its start) passes
        if detached:
            assert layer.last_adjoint_health_ratio <= 0.01 < ctrl.health_refinements[-1]["ratio"]
            assert [e["k"] for e in ctrl.health_refinements] == list(range(2, ctrl.k))
            # The control's gradient is then the physics' to about the adjoint's residual.
            assert torch.linalg.norm(f_in.grad - f_exact.grad) <= 0.02 * torch.linalg.norm(f_exact.grad)
        else:
            assert ctrl.k == 2 and not ctrl.health_refinements
            assert 0.01 < layer.last_adjoint_health_ratio <= 1.0
