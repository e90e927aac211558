"""Networks on DOF vectors: a plain MLP, a residual MLP and a graph convolution over the mesh.

:func:`mlp` maps (B, n_in) to (B, n_out) (an observation to a source, in the
SIP and HIG tasks); :class:`Standardize` in front of it centres and scales
its inputs by statistics of training samples. The other two map a batch of
fields (B, n) on the owned DOFs of a space to (B, n) and learn a correction:
``u + net(u)``, so an untrained network is close to the identity (one heat
step changes a field only a little).

The graph network uses the mesh's connectivity: two DOFs are neighbours when
they share a cell, i.e. when the assembled stiffness matrix couples them.
Each layer adds to its features a mix over the symmetrically normalised
adjacency (with self loops), H + GELU(D^{-1/2} (A + I) D^{-1/2} H W), as in a
residual graph convolutional network, in torch only (one sparse-times-dense
product per layer).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch

from fempdl.iterative.sparse import SparseOperator, sparse_to_torch

__all__ = ["ResidualMLP", "GraphConvNet", "Standardize", "mlp", "normalised_adjacency"]


def mlp(n_in: int, n_out: int, hidden: int, layers: int, activation=torch.nn.GELU) -> torch.nn.Sequential:
    """``layers`` hidden layers of width ``hidden``, each followed by ``activation()``, then a linear output."""
    widths = [n_in] + [hidden] * layers
    blocks = []
    for a, b in zip(widths[:-1], widths[1:]):
        blocks += [torch.nn.Linear(a, b), activation()]
    blocks.append(torch.nn.Linear(widths[-1], n_out))
    return torch.nn.Sequential(*blocks)


class Standardize(torch.nn.Module):
    """x -> (x - mean) / scale per input feature, from samples (N, n) of the inputs.

    scale is each feature's standard deviation, floored at ``relative_floor``
    times the largest one: a feature that hardly varies in the samples (a
    marker value far from where markers go) is not blown up into noise, and a
    constant feature maps to 0. Raw fields share a large common mode and
    spread over orders of magnitude between DOFs; centring and scaling them
    conditions the first layer, which is what a first-order optimizer needs.
    The statistics are buffers: fixed, and saved with the model.
    """

    def __init__(self, samples: torch.Tensor, relative_floor: float = 1e-2):
        super().__init__()
        if samples.ndim != 2 or samples.shape[0] < 2 or samples.shape[1] < 1:
            raise ValueError(f"Standardize needs samples of shape (N >= 2, n >= 1), got {tuple(samples.shape)}")
        if not torch.isfinite(samples).all():
            raise ValueError("Standardize got non-finite samples")
        if not 0.0 < relative_floor <= 1.0:
            raise ValueError(f"relative_floor must be in (0, 1], got {relative_floor}")
        std = samples.std(dim=0)
        largest = float(std.max())
        floor = relative_floor * largest if largest > 0.0 else 1.0
        self.register_buffer("mean", samples.mean(dim=0).detach().clone())
        self.register_buffer("scale", std.clamp_min(floor).detach().clone())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.mean.to(x.dtype)) / self.scale.to(x.dtype)


class ResidualMLP(torch.nn.Module):
    """u + mask * MLP(u): ``layers`` hidden layers of width ``hidden`` with GELU.

    Args:
        mask: optional (n,) weights of the correction per DOF (0 keeps a DOF,
            e.g. a Dirichlet value, as it is).
        start_at_identity: zero the output layer, so the untrained network is
            exactly the identity (a corrector that starts as "no correction").
    """

    def __init__(self, n: int, hidden: int = 128, layers: int = 2, *, mask: torch.Tensor | None = None,
                 start_at_identity: bool = False):
        super().__init__()
        self.net = mlp(n, n, hidden, layers)
        if start_at_identity:
            torch.nn.init.zeros_(self.net[-1].weight)
            torch.nn.init.zeros_(self.net[-1].bias)
        if mask is not None and tuple(mask.shape) != (n,):
            raise ValueError(f"mask must have shape ({n},), got {tuple(mask.shape)}")
        self.register_buffer("mask", None if mask is None else mask.detach().clone())

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        correction = self.net(u)
        return u + (correction if self.mask is None else self.mask.to(u.dtype) * correction)


def normalised_adjacency(pattern: sp.spmatrix) -> torch.Tensor:
    """D^{-1/2} (S + I) D^{-1/2} for the 0/1 pattern S of a (n, n) sparse matrix, as torch CSR."""
    S = sp.csr_matrix(pattern, dtype=np.float64, copy=True)
    S.data[:] = 1.0
    S = (S + sp.identity(S.shape[0], format="csr")).tocsr()
    S.data[:] = 1.0
    d = np.asarray(S.sum(axis=1)).ravel()
    scale = sp.diags(1.0 / np.sqrt(d))
    N = (scale @ S @ scale).tocsr()
    N.sort_indices()
    return sparse_to_torch(N)


class GraphConvNet(torch.nn.Module):
    """u + GCN(u) on the DOF graph; features: the field value and the DOF coordinates.

    Args:
        adjacency: normalised (n, n) adjacency (:func:`normalised_adjacency`).
        coordinates: (n, d) DOF coordinates (fixed input features).
        hidden: channels per layer; layers: number of graph convolutions.
    """

    def __init__(self, adjacency: torch.Tensor, coordinates: np.ndarray, hidden: int = 32, layers: int = 4):
        super().__init__()
        self.register_buffer("coords", torch.as_tensor(coordinates, dtype=torch.float32))
        self._adjacency = adjacency
        self.lift = torch.nn.Linear(1 + coordinates.shape[1], hidden)
        self.convs = torch.nn.ModuleList(torch.nn.Linear(hidden, hidden) for _ in range(layers))
        self.head = torch.nn.Linear(hidden, 1)

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        batch, n = u.shape
        coords = self.coords.to(u.dtype)[:, None, :].expand(n, batch, -1)
        # Node-major features (n, B, hidden): the graph products need no transposed copies.
        h = self.lift(torch.cat([u.T.unsqueeze(-1), coords], dim=-1))
        adjacency = self._operator(u.dtype)
        for conv in self.convs:
            mixed = adjacency @ conv(h).reshape(n, -1)                          # (n, B * hidden)
            # Residual blocks: each layer adds a neighbourhood-mixed update.
            h = h + torch.nn.functional.gelu(mixed.reshape(n, batch, -1))
        return u + self.head(h).squeeze(-1).T

    def _operator(self, dtype) -> SparseOperator:
        """The adjacency as a constant operator; it is symmetric, so it is its own transpose
        (autograd's CSR backward would sort a transposed copy at every step)."""
        if self._adjacency.dtype != dtype:
            self._adjacency = self._adjacency.to(dtype)
            self._op = None
        if getattr(self, "_op", None) is None:
            self._op = SparseOperator(self._adjacency, self._adjacency)
        return self._op
