"""The graph network on the DOF graph: its products and gradients against dense arithmetic."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from fempdl.app.networks import GraphConvNet, normalised_adjacency


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
