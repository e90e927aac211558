"""k_start: PRDP's first cap measured on the loop's inputs and starts, as the smallest K whose capped
solve is within a relative error of converged solves (a k0 of 1 from zero ruined a Newton inverse problem)."""
from __future__ import annotations

import pytest
import torch

from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, SolveLayer, forms
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.prdp import k_start


def relative_error(layer, k, reference, **inputs):
    layer.max_it = k
    with torch.no_grad():
        u = layer(**inputs)
    return float(((u - reference).norm(dim=-1) / reference.norm(dim=-1)).max())


@pytest.fixture(scope="module")
def heat(lshape):
    prob = forms.heat.problem(lshape, controls=("u0",), dt=0.002)
    x = torch.from_numpy(prob.dof_coordinates())
    u0 = torch.stack([torch.sin(3 * x[:, 0]) * torch.cos(2 * x[:, 1]), torch.cos(x[:, 0] + 2 * x[:, 1])])
    return prob, u0


@pytest.mark.parametrize("tolerance", [0.5, 0.05])
def test_linear_k_start_is_the_smallest_cap_within_tolerance(heat, tolerance):
    prob, u0 = heat
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=7))
    cold = k_start(layer, tolerance=tolerance, u0=u0)
    warm = k_start(layer, tolerance=tolerance, u0=u0, initial_guess=u0)
    assert layer.max_it == 7 and layer.stats.forward_solves == 0          # the target is left as it was
    with torch.no_grad():
        reference = SolveLayer(prob, "lu")(u0=u0)
    check = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
    for k, start in ((cold, {}), (warm, {"initial_guess": u0})):
        assert relative_error(check, k, reference, u0=u0, **start) <= tolerance
        if k > 1:
            assert relative_error(check, k - 1, reference, u0=u0, **start) > tolerance
    assert warm < cold          # a warm start needs fewer iterations for the same error


def test_newton_k_start_from_zero_and_from_a_warm_start(lshape):
    prob = forms.nonlinear_diffusion.problem(lshape, controls=("f",), alpha=20.0)
    f = torch.full((prob.control_size("f"),), 20.0, dtype=torch.float64)
    layer = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
    with torch.no_grad():
        solution = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu"))(f=f)
    cold = k_start(layer, tolerance=0.1, f=f)
    warm = k_start(NewtonCaps(layer, "newton"), tolerance=0.1, f=f, initial_guess=0.9 * solution)
    assert layer.max_it == 1 and layer.stats.newton_solves == 0
    check = NonlinearSolveLayer(prob, NewtonOptions(max_it=1, ksp="lu"))
    assert relative_error(check, cold, solution, f=f) <= 0.1 < relative_error(check, cold - 1, solution, f=f)
    assert relative_error(check, warm, solution, f=f, initial_guess=0.9 * solution) <= 0.1
    assert warm < cold and cold > 1       # one Newton step from zero is far from the solution here


def test_k_start_errors(heat, coarse_lshape):
    prob, u0 = heat
    layer = SolveLayer(prob, KSPOptions.preset("jacobi", max_it=1))
    with pytest.raises(ValueError, match="give the inputs to measure k0 on"):
        k_start(layer)
    with pytest.raises(ValueError, match=r"tolerance must be a relative error in \(0, 1\], got 0"):
        k_start(layer, tolerance=0, u0=u0)
    with pytest.raises(ValueError, match="no cap up to k_max=2 brings these solves within a relative error of 0.001"):
        k_start(layer, tolerance=1e-3, k_max=2, u0=u0)
    with pytest.raises(ValueError, match="solves directly"):
        k_start(SolveLayer(prob, "lu"), u0=u0)
    with pytest.raises(TypeError, match="target must be a SolveLayer, a NonlinearSolveLayer, a NewtonCaps, a "
                                        "Rollout or a list of them"):
        k_start(object(), u0=u0)
