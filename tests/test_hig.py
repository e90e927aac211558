"""HIG: the exact limits (gradient descent, Gauss-Newton), truncation, the memory bound, and the toy problem."""
from __future__ import annotations

from mpi4py import MPI
import pytest
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
from fempdl.methods.hig import HIG, half_inverse_update


@pytest.fixture(scope="module")
def poisson_layer():
    problem = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.4), controls=("f",))
    layer = SolveLayer(problem, KSPOptions.preset("lu"))
    yield layer
    layer.close()


def _setup(layer, seed=0):
    """A small MLP predicting the source f from 3 inputs; the outcome is the Poisson solution u."""
    torch.manual_seed(seed)
    n = layer.problem.output_size
    model = torch.nn.Sequential(torch.nn.Linear(3, 6), torch.nn.Tanh(), torch.nn.Linear(6, n)).double()
    inputs = torch.randn(4, 3, dtype=torch.float64)
    target = torch.randn(4, n, dtype=torch.float64) * 0.01

    def physics(f):
        return layer(f=f)

    def loss_fn(u):
        return 0.5 * ((u - target) ** 2).sum()

    return model, inputs, physics, loss_fn


def _flat_params(model):
    return torch.cat([p.detach().reshape(-1) for p in model.parameters()]).clone()


def test_kappa_one_beta_zero_is_gradient_descent(poisson_layer):
    model, inputs, physics, loss_fn = _setup(poisson_layer)
    loss_fn(physics(model(inputs))).backward()
    gradient = torch.cat([p.grad.reshape(-1) for p in model.parameters()])
    before = _flat_params(model)
    HIG(model, lr=0.3, kappa=1.0, beta=0.0, tau=0.0).step(inputs, loss_fn, physics=physics)
    step = _flat_params(model) - before
    assert (step + 0.3 * gradient).norm() <= 1e-10 * (0.3 * gradient).norm()


def test_kappa_minus_one_is_the_gauss_newton_pseudo_inverse_step(poisson_layer):
    model, inputs, physics, loss_fn = _setup(poisson_layer, seed=1)
    before = _flat_params(model)
    names = [name for name, _ in model.named_parameters()]
    shapes = [p.shape for p in model.parameters()]

    def outcomes(flat):   # the independent Jacobian: autograd row by row through the layer
        params, offset = {}, 0
        for name, shape in zip(names, shapes):
            params[name] = flat[offset:offset + shape.numel()].reshape(shape)
            offset += shape.numel()
        return physics(torch.func.functional_call(model, params, (inputs,))).reshape(-1)

    jacobian = torch.autograd.functional.jacobian(outcomes, before)
    y = outcomes(before).detach().requires_grad_(True)
    (g,) = torch.autograd.grad(loss_fn(y.reshape(4, -1)), y)
    expected = -0.5 * torch.linalg.pinv(jacobian, rtol=1e-10) @ g

    hig = HIG(model, lr=0.5, kappa=-1.0, beta=0.0, tau=1e-10)
    hig.step(inputs, loss_fn, physics=physics)
    step = _flat_params(model) - before
    assert (step - expected).norm() <= 1e-8 * expected.norm()
    assert hig.last_rank == int((torch.linalg.svdvals(jacobian) > 1e-10 * torch.linalg.svdvals(jacobian)[0]).sum())


def test_a_linear_physics_jacobian_computed_once_is_the_same(poisson_layer):
    model, inputs, physics, _ = _setup(poisson_layer, seed=2)
    hig = HIG(model)
    _, per_sample = hig.jacobian(inputs, physics)
    _, shared = hig.jacobian(inputs, physics, linear_physics=True)
    assert (per_sample - shared).abs().max() <= 1e-12 * per_sample.abs().max()


def test_truncation_drops_the_singular_values_below_tau():
    torch.manual_seed(0)
    U, _ = torch.linalg.qr(torch.randn(6, 3, dtype=torch.float64))
    V, _ = torch.linalg.qr(torch.randn(5, 3, dtype=torch.float64))
    S = torch.tensor([2.0, 1e-3, 1e-8], dtype=torch.float64)
    J, g = U @ torch.diag(S) @ V.T, torch.randn(6, dtype=torch.float64)

    def kept(count, kappa):
        return sum(S[i] ** kappa * (U[:, i] @ g) * V[:, i] for i in range(count))

    for tau, rank in ((1e-5, 2), (1e-2, 1), (0.0, 3)):
        update, singular, got_rank = half_inverse_update(J, g, kappa=-0.5, tau=tau)
        assert got_rank == rank
        assert torch.allclose(singular[:3], S, rtol=1e-6) and singular[3:].abs().max() < 1e-12
        assert (update - kept(rank, -0.5)).norm() <= 1e-6 * kept(rank, -0.5).norm()
    # beta = -1 - kappa scales the largest singular value to one.
    update, _, _ = half_inverse_update(J, g, kappa=-0.5, beta=-0.5, tau=1e-5)
    assert torch.allclose(update, 2.0 ** -0.5 * kept(2, -0.5), rtol=1e-6)


def test_the_gram_path_equals_the_svd_and_knows_its_resolution():
    torch.manual_seed(1)
    U, _ = torch.linalg.qr(torch.randn(20, 20, dtype=torch.float64))
    V, _ = torch.linalg.qr(torch.randn(60, 20, dtype=torch.float64))
    S = torch.logspace(0, -4, 20, dtype=torch.float64)
    J, g = U @ torch.diag(S) @ V.T, torch.randn(20, dtype=torch.float64)
    for kappa, beta in ((-0.5, 0.0), (-1.0, 0.0), (1.0, 0.0), (-0.5, -0.5)):
        by_svd, _, rank_svd = half_inverse_update(J, g, kappa=kappa, beta=beta, tau=1e-3, method="svd")
        by_gram, singular, rank_gram = half_inverse_update(J, g, kappa=kappa, beta=beta, tau=1e-3, method="gram")
        assert rank_svd == rank_gram == int((S > 1e-3).sum())
        assert torch.allclose(singular, S, rtol=1e-6, atol=0)
        assert (by_gram - by_svd).norm() <= 1e-8 * by_svd.norm()
    # A singular value of 1e-8 max is below the Gram matrix's resolution (sqrt(eps * 60) = 1.2e-7):
    # "gram" drops it even at tau = 0; "auto" sees that tau asks for it and takes the SVD.
    S[-1] = 1e-8
    J = U @ torch.diag(S) @ V.T
    assert half_inverse_update(J, g, tau=0.0, method="gram")[2] == 19
    assert half_inverse_update(J, g, tau=1e-9, method="auto")[2] == 20
    assert half_inverse_update(J, g, tau=1e-5, method="auto")[2] == half_inverse_update(J, g, tau=1e-5)[2] == 19
    with pytest.raises(ValueError, match="method must be 'auto', 'svd' or 'gram'"):
        half_inverse_update(J, g, method="qr")
    J[3, 5] = float("nan")           # a NaN row must not be dropped as if it were a zero row
    with pytest.raises(ValueError, match="holds NaN or inf"):
        half_inverse_update(J, g)


def test_a_jacobian_over_the_memory_bound_is_refused_with_its_size(poisson_layer):
    model, inputs, physics, loss_fn = _setup(poisson_layer)
    with pytest.raises(MemoryError, match=r"HIG needs a \(\d+ x \d+\) Jacobian .* MiB, more than "
                                          r"max_jacobian_bytes = 0.0 MiB"):
        HIG(model, max_jacobian_bytes=1000).step(inputs, loss_fn, physics=physics)
    with pytest.raises(ValueError, match="lr must be > 0"):
        HIG(model, lr=0.0)


def _toy(method, lr, steps=200, gamma=0.01):
    """Paper 002, section 2.1: fit (sin 6x, cos 9x) with a 7-neuron tanh network, loss scaled by gamma."""
    torch.manual_seed(0)
    x = torch.rand(128, 1, dtype=torch.float64) * 2 - 1
    target = torch.cat([torch.sin(6 * x), torch.cos(9 * x)], 1)
    model = torch.nn.Sequential(torch.nn.Linear(1, 7), torch.nn.Tanh(), torch.nn.Linear(7, 2)).double()

    def physics(out):
        return torch.cat([out[:, :1], gamma * out[:, 1:]], 1)

    def loss_fn(y):
        return 0.5 * ((y - target) ** 2).sum(1).mean()

    if method == "adam":
        optimizer = torch.optim.Adam(model.parameters(), lr=lr)
        for _ in range(steps):
            loss = loss_fn(physics(model(x)))
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()
    else:
        hig = HIG(model, lr=lr, tau=1e-6)
        for _ in range(steps):
            hig.step(x, loss_fn, physics=physics)
    with torch.no_grad():
        return float(loss_fn(physics(model(x))))


def test_hig_beats_adam_on_the_ill_conditioned_toy_problem():
    start = _toy("adam", 1e-3, steps=0)
    best_adam = min(_toy("adam", lr) for lr in (1e-3, 1e-2, 3e-2))
    hig = _toy("hig", 1.0)
    assert hig < 0.8 * best_adam < start
