"""A preconditioner set up once per call for per-sample matrices (KSPOptions.lag_preconditioner)."""
from __future__ import annotations

import pytest
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

from helpers import build, control_values


@pytest.fixture(scope="module")
def heat(coarse_lshape):
    return build("heat", coarse_lshape, controls=("u0", "kappa"))


def _options(**kw):
    return KSPOptions(ksp_type="gmres", pc_type="ilu", gmres_restart=30, engine="petsc", **kw)


def test_lagged_preconditioner_converges_to_the_same_solution_and_gradient(heat):
    u0 = control_values(heat, "u0", 4, seed=1)
    kappa = (control_values(heat, "kappa", 4, seed=1) * torch.linspace(1, 3, 4)[:, None]).requires_grad_()
    results = []
    for lag in (False, True):
        layer = SolveLayer(heat, _options(max_it=None, rtol=1e-12, lag_preconditioner=lag))
        out = layer(u0=u0, kappa=kappa)
        grad = torch.autograd.grad(out.square().sum(), kappa)[0]
        results.append((out, grad, layer.stats.forward_iterations))
    (u_fresh, g_fresh, its_fresh), (u_lag, g_lag, its_lag) = results
    assert torch.allclose(u_lag, u_fresh, rtol=1e-9, atol=1e-12)
    assert torch.allclose(g_lag, g_fresh, rtol=1e-8, atol=1e-12)
    # ILU(0) of the first sample's matrix is a worse preconditioner for the others.
    assert its_lag > its_fresh


def test_lagged_capped_solves_run_exactly_k_iterations(heat):
    u0 = control_values(heat, "u0", 3, seed=2)
    kappa = control_values(heat, "kappa", 3, seed=2).requires_grad_()
    layer = SolveLayer(heat, _options(max_it=4, lag_preconditioner=True))
    layer(u0=u0, kappa=kappa).sum().backward()
    assert (layer.stats.forward_iterations, layer.stats.backward_iterations) == (12, 12)
    assert layer.system._solver.reuse_preconditioner is False      # nothing lags into the next call


def test_lag_preconditioner_is_validated():
    with pytest.raises(TypeError, match="lag_preconditioner"):
        KSPOptions(lag_preconditioner="yes")
