"""The graph network on the DOF graph: its products and gradients against dense arithmetic."""
from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from fempdl.app.tasks.networks import GraphConvNet, Standardize, normalised_adjacency


def _dense_reference(net: GraphConvNet, A: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """The same network written batch-major with a dense adjacency."""
    batch, n = u.shape
    h = net.lift(torch.cat([u.unsqueeze(-1), net.coords.to(u.dtype).expand(batch, n, -1)], dim=-1))
    for conv in net.convs:
        h = h + torch.nn.functional.gelu(torch.einsum("ij,bjc->bic", A, conv(h)))
    return u + net.head(h).squeeze(-1)


def test_graph_network_matches_dense_arithmetic_with_gradients():
    rng = np.random.default_rng(0)
    n = 30
    pattern = sp.random(n, n, density=0.15, random_state=1, format="csr")
    pattern = pattern + pattern.T + sp.identity(n)
    adjacency = normalised_adjacency(pattern).to(torch.float64)
    torch.manual_seed(0)
    net = GraphConvNet(adjacency, rng.random((n, 2)), hidden=5, layers=3).double()
    u = torch.randn(4, n, dtype=torch.float64, requires_grad=True)
    out = net(u)
    reference = _dense_reference(net, adjacency.to_dense(), u)
    assert torch.allclose(out, reference, rtol=1e-12, atol=1e-12)
    g = torch.randn_like(out)
    grads = torch.autograd.grad(out, [u, *net.parameters()], g)
    expected = torch.autograd.grad(reference, [u, *net.parameters()], g)
    for a, b in zip(grads, expected):
        assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(lambda x: net(x), (u[:2].detach().requires_grad_(),))


def test_standardize_centres_and_scales_each_feature_with_a_floor_for_still_ones():
    torch.manual_seed(0)
    samples = torch.randn(50, 4, dtype=torch.float64) * torch.tensor([3.0, 0.5, 1e-6, 0.0], dtype=torch.float64) + 7.0
    standardize = Standardize(samples, relative_floor=0.01)
    z = standardize(samples)
    torch.testing.assert_close(z.mean(dim=0), torch.zeros(4, dtype=torch.float64), atol=1e-12, rtol=0)
    std = z.std(dim=0)
    torch.testing.assert_close(std[:2], torch.ones(2, dtype=torch.float64))
    # a feature that hardly moves is scaled by the floor (1% of the largest spread), not blown up
    floor = 0.01 * float(samples[:, 0].std())
    assert abs(float(standardize.scale[2]) - floor) < 1e-12 and float(std[2]) < 1e-4
    assert float(z[:, 3].abs().max()) == 0.0                              # a constant feature maps to 0
    assert set(standardize.state_dict()) == {"mean", "scale"}             # saved with the model


@pytest.mark.parametrize("samples, floor, fragment", [
    (torch.zeros(1, 3), 0.01, "samples of shape (N >= 2, n >= 1)"),
    (torch.zeros(5), 0.01, "samples of shape (N >= 2, n >= 1), got (5,)"),
    (torch.zeros(4, 0), 0.01, "samples of shape (N >= 2, n >= 1), got (4, 0)"),
    (torch.tensor([[0.0, float("nan")], [1.0, 2.0]]), 0.01, "non-finite"),
    (torch.tensor([[0.0, float("inf")], [1.0, 2.0]]), 0.01, "non-finite"),
    (torch.zeros(4, 3), 0.0, "relative_floor must be in (0, 1]"),
    (torch.zeros(4, 3), 1.5, "relative_floor must be in (0, 1]"),
])
def test_standardize_refuses_unusable_samples(samples, floor, fragment):
    with pytest.raises(ValueError, match=re.escape(fragment)):
        Standardize(samples, relative_floor=floor)


def test_standardize_of_constant_samples_is_a_shift():
    standardize = Standardize(torch.full((3, 2), 5.0))
    torch.testing.assert_close(standardize(torch.tensor([[6.0, 4.0]])), torch.tensor([[1.0, -1.0]]))
