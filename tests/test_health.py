"""Solver health (fempdl/solve/health.py): a training call whose capped solves are garbage (residual grown,
or not shrunk below the limit) refines PRDP's K at once and is solved again before it returns."""
import dataclasses
import warnings

from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import PRDP, KSPOptions, NewtonOptions, NonlinearSolveLayer, PRDPSettings, SolveLayer, forms, mesh
from fempdl.layer.healthy_calls import HEALTH_EVERY
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.solve.health import CallHealth, HealthCheck
from fempdl.solve.stats import SolverWarning


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.1)


@pytest.fixture(scope="module")
def stiff_heat(lshape):
    """A backward-Euler step of -div((1 + 20 u^2) grad u): plain Newton from zero overshoots at first."""
    problem = forms.nonlinear_diffusion.problem(lshape, controls=("u0",), alpha=20.0, f=0.0, dt=0.01)
    x = torch.from_numpy(problem.dof_coordinates())
    u0 = torch.stack([2.0 * torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1]),
                      0.01 * torch.cos(x[:, 0])])                       # a stiff sample and a mild one
    return problem, u0


def newton_ratios(problem, u0, caps):
    """max over samples of ||F(u_K)|| / ||F(u_0)|| for each K in caps, from no-grad solves."""
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"))
    ratios = []
    for k in caps:
        layer.max_it = k
        worst = 0.0
        for sample in u0:
            with torch.no_grad():
                layer(u0=sample)
            norms = layer.stats.last_newton.residual_norms
            worst = max(worst, norms[-1] / norms[0])
        ratios.append(worst)
    layer.close()
    return ratios


def test_a_garbage_newton_solve_refines_at_once_and_the_backward_runs_at_the_refined_cap(stiff_heat):
    problem, u0 = stiff_heat
    ratios = newton_ratios(problem, u0, range(1, 9))
    healthy = next(k for k, rho in zip(range(1, 9), ratios) if rho <= 1.0)
    assert ratios[0] > 1.0 and healthy > 1                                # K = 1 overshoots: garbage
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"))
    ctrl = PRDP(NewtonCaps(layer, "newton"), k0=1, k_cap=20)
    x = u0.clone().requires_grad_()
    with warnings.catch_warnings():
        warnings.simplefilter("error", SolverWarning)
        u = layer(u0=x)
        u.square().sum().backward()
    assert ctrl.k == layer.max_it == healthy
    assert [event["k"] for event in ctrl.health_refinements] == list(range(1, healthy))
    assert [event["ratio"] for event in ctrl.health_refinements] == pytest.approx(ratios[:healthy - 1], rel=1e-10)
    assert all(event["step"] == 0 for event in ctrl.health_refinements)
    # The same call on a layer at that cap without a health check: the same solution and gradient.
    plain = NonlinearSolveLayer(problem, NewtonOptions(max_it=healthy, ksp="lu"))
    y = u0.clone().requires_grad_()
    v = plain(u0=y)
    v.square().sum().backward()
    torch.testing.assert_close(u, v, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(x.grad, y.grad, rtol=1e-10, atol=1e-14)
    for lay in (layer, plain):
        lay.close()


def test_no_grad_calls_and_a_controller_without_health_never_refine(stiff_heat):
    problem, u0 = stiff_heat
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"))
    ctrl = PRDP(NewtonCaps(layer, "newton"), k0=1, k_cap=20)
    with torch.no_grad():                                    # a validation: trains nothing, refines nothing
        layer(u0=u0)
    assert ctrl.k == layer.max_it == 1 and not ctrl.health_refinements
    off = PRDP(NewtonCaps(layer, "newton"), k0=1, k_cap=20, health=None)
    assert layer.health is None                                             # the old check taken away
    layer(u0=u0.clone().requires_grad_())
    assert off.k == 1 and not off.health_refinements and layer.last_health_ratio is None
    layer.close()


def test_unrolled_newton_refines_too_and_stays_exact_k(stiff_heat):
    problem, u0 = stiff_heat
    healthy = next(k for k, rho in zip(range(1, 9), newton_ratios(problem, u0[:1], range(1, 9))) if rho <= 1.0)
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"), diff="unrolled")
    ctrl = PRDP(NewtonCaps(layer, "newton"), k0=1, k_cap=20)
    layer(u0=u0[0].clone().requires_grad_()).sum().backward()
    assert ctrl.k == healthy and layer.stats.last_newton.steps == healthy
    layer.close()


@pytest.fixture(scope="module")
def poisson(lshape):
    problem = forms.poisson.problem(lshape, controls=("f",))
    x = torch.from_numpy(problem.dof_coordinates())
    f = torch.stack([1.0 + x[:, 0], torch.sin(4 * x[:, 1])])
    return problem, f


# Richardson with Jacobi scaled by 1.9: the preconditioned operator's largest eigenvalues pass 2, so
# the iteration diverges; from a smooth right-hand side its residual grows from the fifth step on.
DIVERGING = dict(petsc_options={"ksp_richardson_scale": 1.9})


@pytest.mark.parametrize("engine, diff", [("petsc", "implicit"), ("batched", "implicit"), ("petsc", "unrolled")])
def test_a_diverging_linear_solve_refines_once_then_warns(poisson, engine, diff):
    problem, f = poisson
    options = KSPOptions.preset("jacobi", max_it=5, engine=engine, **DIVERGING)
    layer = SolveLayer(problem, options, diff=diff)
    ctrl = PRDP(layer, k0=5, k_cap=50, growth=1.0)
    with pytest.warns(SolverWarning, match=r"refining did not lower it .*the iteration diverges") as caught:
        layer(f=f.clone().requires_grad_()).sum().backward()
    # The forward refines once and warns; an implicit backward's adjoint, the same iteration transposed,
    # diverges too: once more, and a warning of its own. An unrolled backward solves nothing.
    adjoint = [(6, 7)] if diff == "implicit" else []
    assert [(e["k"], e["to"]) for e in ctrl.health_refinements] == [(5, 6)] + adjoint and ctrl.k == 6 + len(adjoint)
    assert sum("capped adjoint solve" in str(w.message) for w in caught) == len(adjoint)
    # rho from the solutions themselves: the worst sample's ||b - A u_5|| / ||b||
    A = layer.system.constant_matrix()
    b_base, rhs = layer.system.affine_rhs(frozenset({"f"}))
    b = np.stack([b_base + rhs["f"] @ fi.numpy() for fi in f])
    layer.max_it = 5
    with torch.no_grad():
        u = layer(f=f).numpy()
    rho = max(np.linalg.norm(bi - A @ ui) / np.linalg.norm(bi) for bi, ui in zip(b, u))
    assert ctrl.health_refinements[0]["ratio"] == pytest.approx(rho, rel=1e-8)
    layer.close()


def test_a_garbage_solve_at_k_cap_warns_and_is_kept_and_calls_are_measured_every_eighth(poisson):
    problem, f = poisson
    layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=3))
    ctrl = PRDP(layer, k0=3, k_cap=3, health=1e-3)     # three Jacobi steps never shrink a residual 1000-fold
    warned = []
    for _ in range(2 * HEALTH_EVERY + 1):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            layer(f=f.clone().requires_grad_())
        warned.append([str(w.message) for w in caught if issubclass(w.category, SolverWarning)])
    assert all("cannot rise further (k_cap)" in w[0] for w in warned[::HEALTH_EVERY])
    assert [bool(w) for w in warned] == [i % HEALTH_EVERY == 0 for i in range(2 * HEALTH_EVERY + 1)]
    assert ctrl.k == 3 and not ctrl.health_refinements and layer.last_health_ratio > 0.5
    layer.max_it = 2                                   # new caps: measured at once
    with pytest.warns(SolverWarning, match=r"at Caps\(max_it=2\)"):
        layer(f=f.clone().requires_grad_())
    layer.close()


def test_a_warm_start_at_the_solution_is_healthy(poisson):
    """Its residual starts and stays at round-off: the ratio is noise, the floor says solved."""
    problem, f = poisson
    exact = SolveLayer(problem, "lu")
    with torch.no_grad():
        u = exact(f=f)
    layer = SolveLayer(problem, KSPOptions.preset("jacobi", max_it=2))
    ctrl = PRDP(layer, k0=2, k_cap=50, health=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SolverWarning)
        layer(f=f.clone().requires_grad_(), initial_guess=u)
    assert ctrl.k == 2 and not ctrl.health_refinements and layer.last_health_ratio == 0.0
    for lay in (exact, layer):
        lay.close()


def test_health_settings_are_checked_and_saved():
    for bad in (0.0, -1.0, float("inf"), True, "1"):
        with pytest.raises(ValueError, match="health must be a finite residual ratio"):
            PRDPSettings(health=bad)
    with pytest.raises(ValueError, match="a health limit must be a finite number > 0"):
        HealthCheck(0.0, lambda rho: False)
    ctrl = PRDP(None, k0=1, k_cap=4)
    assert ctrl.health == 1.0 and ctrl.refine_for_health(3.0) and ctrl.k == 2
    state = ctrl.state_dict()
    assert state["health_refinements"] == [{"step": 0, "k": 1, "to": 2, "ratio": 3.0}]
    again = PRDP(None, k0=1, k_cap=4)
    again.load_state_dict(state)
    assert again.k == 2 and again.health_refinements == ctrl.health_refinements
    old = {**state, "settings": {k: v for k, v in state["settings"].items() if k != "health"}}
    del old["health_refinements"]
    again.load_state_dict(old)                  # saved before health existed: resumes
    assert again.health_refinements == []
    with pytest.raises(ValueError, match="health"):
        PRDP(None, k0=1, k_cap=4, health=0.5).load_state_dict(state)
    ctrl.k = 4
    assert not ctrl.refine_for_health(3.0)      # at k_cap


def test_a_solve_measures_into_the_call_health_it_is_handed_and_keeps_none(stiff_heat):
    """The measured ratio is the call's return channel: the system keeps no health state between calls."""
    problem, u0 = stiff_heat
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=1, ksp="lu"))
    arrays = {"u0": u0.numpy()}
    health = CallHealth(1.0)
    layer.system.solve(arrays, 2, health=health)
    assert health.ratio == pytest.approx(max(newton_ratios(problem, u0, [1])), rel=1e-12)
    assert not any("health" in name for name in vars(layer.system))
    layer.close()


def test_call_health_ratio():
    health = CallHealth(1.0)
    health.add(2.0, 4.0, lambda: pytest.fail("the floor is needed only above the limit"))
    health.add(3.0, 2.0, lambda: 1e-300)
    assert health.ratio == 1.5
    health.add(1e-13, 1e-14, lambda: 1e-12)     # at round-off: healthy
    health.add(float("nan"), 1.0, lambda: 1.0)
    assert health.ratio == float("inf")
    assert dataclasses.is_dataclass(HealthCheck)
