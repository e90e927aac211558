"""SIP: the proxy loss, Theorem 1 of the physical-gradients paper, and the inverse updates on FEM layers."""
from __future__ import annotations

from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import forms, mesh
from fempdl.app.tasks.data import smooth_fields
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
from fempdl.methods.sip import (
    ExactLinearInverse,
    GaussNewtonInverse,
    GradientStep,
    TikhonovInverse,
    proxy_loss,
    sip_step,
)

LU = KSPOptions.preset("lu")


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.15)


def _poisson(lshape, g=0.0):
    return forms.poisson.problem(lshape, controls=("f",), g=g)


def _sources(problem, count, seed=0):
    return torch.as_tensor(smooth_fields(problem.dof_coordinates(), count, 4, np.random.default_rng(seed)))


def _free(problem):
    return np.setdiff1d(np.arange(problem.output_size), problem.bc_dofs)


def test_proxy_loss_gradient_is_the_update_and_stops_at_x_star():
    x0 = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    x_star = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    proxy_loss(x0, x_star).backward()
    assert torch.equal(x0.grad, (x0 - x_star).detach())
    assert x_star.grad is None


def test_sip_with_a_unit_gradient_step_is_backpropagation(lshape):
    """Paper 001, Theorem 1: with x* = x0 - dL/dx0 the proxy loss has the same weight gradient as L."""
    problem = _poisson(lshape)
    layer = SolveLayer(problem, LU)
    n = problem.output_size
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Linear(n, 16), torch.nn.Tanh(), torch.nn.Linear(16, n)).double()
    inputs = torch.randn(4, n, dtype=torch.float64)
    y_target = layer(f=_sources(problem, 4))

    x0 = model(inputs)
    (0.5 * ((layer(f=x0) - y_target) ** 2).sum()).backward()
    backprop = [p.grad.clone() for p in model.parameters()]
    model.zero_grad()

    x0 = model(inputs)
    proxy_loss(x0, GradientStep(layer, "f", eta=1.0)(x0.detach(), y_target)).backward()
    for p, reference in zip(model.parameters(), backprop):
        assert (p.grad - reference).norm() <= 1e-12 * reference.norm()
    layer.close()


@pytest.mark.parametrize("g", [0.0, 0.7])
def test_exact_poisson_inverse_lands_on_the_target(lshape, g):
    problem = _poisson(lshape, g=g)
    layer = SolveLayer(problem, LU)
    y_target = layer(f=_sources(problem, 3, seed=1))
    x0 = _sources(problem, 3, seed=2)
    inverse = ExactLinearInverse(layer, "f")
    x_star = inverse(x0, y_target)
    error = (layer(f=x_star) - y_target).abs().max() / y_target.abs().max()
    assert error < 1e-11
    # eta scales the step: half a step leaves half of the error (the map is affine).
    half = ExactLinearInverse(layer, "f", eta=0.5)(x0, y_target)
    remaining = layer(f=half) - y_target
    assert torch.allclose(remaining, 0.5 * (layer(f=x0) - y_target), atol=1e-11 * y_target.abs().max())
    layer.close()


def test_the_exact_inverse_refuses_controls_it_cannot_invert(lshape):
    problem = forms.poisson.problem(lshape, controls=("f", "kappa"))
    layer = SolveLayer(problem, LU)
    with pytest.raises(ValueError, match="'kappa' is not"):
        ExactLinearInverse(layer, "kappa")
    with pytest.raises(ValueError, match="unknown control 'u0'"):
        ExactLinearInverse(layer, "u0")
    with pytest.raises(ValueError, match=r"the matrix depends on \['kappa'\]"):
        ExactLinearInverse(layer, "f", fixed={"kappa": torch.ones(problem.control_size("kappa"))})
    with pytest.raises(ValueError, match="'kappa' is not"):
        GaussNewtonInverse(layer, "kappa")
    with pytest.raises(ValueError, match="damping must be >= 0"):
        GaussNewtonInverse(layer, "f", damping=-1.0)
    with pytest.raises(ValueError, match="'kappa' is not"):
        TikhonovInverse(layer, "kappa", damping=1e-2)
    with pytest.raises(ValueError, match="damping must be >= 0"):
        TikhonovInverse(layer, "f", damping=float("nan"))
    with pytest.raises(ValueError, match=r"the fixed inputs \['kappa'\] have a batch dimension"):
        TikhonovInverse(layer, "f", damping=1e-2, fixed={"kappa": torch.ones(2, problem.control_size("kappa"))})
    n_free = len(_free(problem))
    expected_mib = 8 * (2 * problem.output_size + n_free) * n_free / 2**20
    with pytest.raises(MemoryError, match=rf"\({problem.output_size} x {n_free}\) Jacobian and its SVD: "
                                          rf"{expected_mib:.1f} MiB, more than max_matrix_bytes = 0.1 MiB; "
                                          "use GaussNewtonInverse"):
        TikhonovInverse(layer, "f", damping=1e-2, max_matrix_bytes=2**20 // 10)
    layer.close()


def test_gauss_newton_inverse_runs_its_cap_and_converges_to_the_target(lshape):
    problem = _poisson(lshape)
    layer = SolveLayer(problem, LU)
    y_target = layer(f=_sources(problem, 2, seed=3))
    x0 = torch.zeros(2, problem.control_size("f"), dtype=torch.float64)
    errors = {}
    for cap in (2, 10, 60):
        inverse = GaussNewtonInverse(layer, "f", max_it=cap)
        x_star = inverse(x0, y_target)
        assert inverse.last_iterations == cap
        errors[cap] = float((layer(f=x_star) - y_target).norm() / y_target.norm())
    assert errors[2] > errors[10] > errors[60]
    assert errors[60] < 1e-3 * errors[2]
    # Stopping on a tolerance ends earlier than the cap.
    early = GaussNewtonInverse(layer, "f", max_it=500, rtol=1e-6)
    early(x0, y_target)
    assert 10 < early.last_iterations < 500
    layer.close()


def test_prdp_raises_the_gauss_newton_cap_when_the_metric_plateaus(lshape):
    from fempdl.methods.prdp import PRDP

    problem = _poisson(lshape)
    layer = SolveLayer(problem, LU)
    y_target = layer(f=_sources(problem, 2, seed=3))
    x0 = torch.zeros(2, problem.control_size("f"), dtype=torch.float64)
    inverse = GaussNewtonInverse(layer, "f", max_it=50)
    controller = PRDP(inverse, k0=2, dk=3, delta=2, ema_window=1, tau_step=0.95, tau_stop=0.9)
    assert inverse.max_it == 2
    inverse(x0, y_target)
    assert inverse.last_iterations == 2
    for metric in (1.0, 0.5, 0.499):        # progress since the start, then a plateau: K 2 -> 5
        controller.step(metric)
    assert inverse.max_it == 5
    inverse(x0, y_target)
    assert inverse.last_iterations == 5
    layer.close()


def test_damped_heat_inverse_stays_bounded_where_the_exact_one_amplifies_noise(lshape):
    """A heat step damps mode k by 1/(1 + dt lambda_k); its exact inverse multiplies noise by up to
    1 + dt lambda_max. The Tikhonov-damped Gauss-Newton inverse keeps the noise at most 1/(2 sqrt(alpha))."""
    problem = forms.heat.problem(lshape, controls=("u0",), dt=0.05)
    layer = SolveLayer(problem, LU)
    u0_true = _sources(problem, 2, seed=4)
    u0_true[:, problem.bc_dofs] = 0.0    # the inverses keep x0's (zero) values there
    clean = layer(u0=u0_true)
    noise = 1e-2 * clean.abs().max() * torch.randn(clean.shape, generator=torch.Generator().manual_seed(0),
                                                   dtype=torch.float64)
    noise[:, problem.bc_dofs] = 0.0
    y_noisy = clean + noise
    x0 = torch.zeros_like(u0_true)
    exact = ExactLinearInverse(layer, "u0")(x0, y_noisy)
    damped = GaussNewtonInverse(layer, "u0", damping=1e-2, max_it=200, rtol=1e-10)(x0, y_noisy)

    def error(x):
        return float((x - u0_true).norm() / u0_true.norm())

    # Exact on clean data, noise amplified by the backward heat equation on noisy data.
    assert error(ExactLinearInverse(layer, "u0")(x0, clean)) < 1e-10
    assert error(exact) > 4.0 * error(damped)   # measured 0.59 against 0.10
    assert error(damped) < 0.15
    layer.close()


def test_tikhonov_inverse_is_converged_gauss_newton_and_bounds_the_gain(lshape):
    """The SVD solves the damped normal equations that Gauss-Newton CG iterates on: equal once CG has
    converged. No residual component is amplified by more than 1/(2 sqrt(alpha))."""
    problem = forms.heat.problem(lshape, controls=("u0",), dt=0.05)
    layer = SolveLayer(problem, LU)
    y_target = layer(u0=_sources(problem, 3, seed=6))
    y_target = y_target + 1e-2 * torch.randn(y_target.shape, generator=torch.Generator().manual_seed(1),
                                             dtype=torch.float64)
    x0 = _sources(problem, 3, seed=7)
    tikhonov = TikhonovInverse(layer, "u0", damping=1e-2, eta=0.8)
    x_star = tikhonov(x0, y_target)
    converged = GaussNewtonInverse(layer, "u0", damping=1e-2, max_it=300, rtol=1e-13, eta=0.8)(x0, y_target)
    assert (x_star - converged).norm() <= 1e-9 * (converged - x0).norm()
    s = tikhonov.singular_values
    assert len(s) == len(_free(problem)) and bool((s[:-1] >= s[1:]).all())
    # For a heat step sigma_k = 1 / (1 + dt lambda_k) (in the Euclidean sense only roughly): all in (0, 1].
    assert 0.0 < float(s[-1]) < 0.1 * float(s[0]) and float(s[0]) <= 1.0 + 1e-12
    gain = (x_star - x0).norm(dim=-1) / (0.8 * (y_target - layer(u0=x0)).norm(dim=-1))
    assert bool((gain <= 1.0 / (2.0 * 1e-2 ** 0.5) + 1e-12).all())
    # The Dirichlet DOFs keep x0's values.
    assert torch.equal(x_star[:, problem.bc_dofs], x0[:, problem.bc_dofs])
    layer.close()


def test_undamped_tikhonov_inverse_is_the_exact_inverse(lshape):
    problem = _poisson(lshape, g=0.3)
    layer = SolveLayer(problem, LU)
    y_target = layer(f=_sources(problem, 2, seed=8))
    x0 = _sources(problem, 2, seed=9)
    x_star = TikhonovInverse(layer, "f", damping=0.0)(x0, y_target)
    assert (x_star - ExactLinearInverse(layer, "f")(x0, y_target)).norm() <= 1e-9 * (x_star - x0).norm()
    assert (layer(f=x_star) - y_target).abs().max() <= 1e-10 * y_target.abs().max()
    layer.close()


def test_sip_training_with_the_exact_inverse_learns_a_linear_source_map(lshape):
    """A linear network trained by SIP on the Poisson inverse problem: x error falls fast."""
    problem = _poisson(lshape)
    layer = SolveLayer(problem, LU)
    sources = _sources(problem, 8, seed=5).float()
    with torch.no_grad():
        observations = layer(f=sources.double()).float()
    torch.manual_seed(0)
    n = problem.output_size
    model = torch.nn.Linear(n, n)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    inverse = ExactLinearInverse(layer, "f")

    def x_error():
        with torch.no_grad():
            return float((model(observations) - sources).norm() / sources.norm())

    start = x_error()
    for _ in range(30):
        sip_step(model, optimizer, observations, observations, inverse)
    assert x_error() < 0.5 * start
    layer.close()
