"""Sparse matrices in torch: CSR copies of SciPy/PETSc matrices, and a constant
operator whose products are differentiable in the dense factor only.

Shapes: an operator is (n, m); it multiplies dense (m, B) blocks.
"""
from __future__ import annotations

import warnings

import numpy as np
import scipy.sparse as sp
import torch

__all__ = ["sparse_to_torch", "torch_to_scipy", "SparseOperator"]


def sparse_to_torch(M: sp.csr_matrix, index_dtype=None) -> torch.Tensor:
    """A scipy CSR matrix as a float64 torch CSR tensor (copies). Indices are int32
    where they fit (``index_dtype=None``), which spares torch's CPU sparse product a
    conversion of the indices per product."""
    if index_dtype is None:
        index_dtype = np.int32 if max(M.nnz, *M.shape) < 2 ** 31 - 1 else np.int64
    with warnings.catch_warnings():
        # torch flags CSR support as beta; sparse @ dense used here is stable.
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta")
        return torch.sparse_csr_tensor(
            torch.from_numpy(M.indptr.astype(index_dtype)), torch.from_numpy(M.indices.astype(index_dtype)),
            torch.from_numpy(M.data.astype(np.float64)), size=M.shape, check_invariants=False)


def torch_to_scipy(T: torch.Tensor) -> sp.csr_matrix:
    """A torch CSR tensor as a scipy CSR matrix (sharing its memory)."""
    return sp.csr_matrix((T.values().numpy(), T.col_indices().numpy(), T.crow_indices().numpy()),
                         shape=tuple(T.shape))


class _ConstantSparseMatMul(torch.autograd.Function):
    """A @ X for a constant sparse A; backward A^T @ grad with a stored transpose.

    torch's own sparse @ dense keeps X for a gradient of A that is never
    needed here; this keeps nothing, so a linear iteration such as Jacobi
    stores no per-iteration state at all."""

    @staticmethod
    def forward(ctx, X, A, At):
        ctx.At = At
        return A @ X

    @staticmethod
    def backward(ctx, grad):
        return ctx.At @ grad, None, None


class SparseOperator:
    """A constant sparse matrix (torch CSR) and its transpose, for ``A @ X`` in
    differentiable iterations: gradients flow to X only."""

    def __init__(self, A: torch.Tensor, At: torch.Tensor):
        self.A, self.At = A, At
        self.shape = A.shape

    def __matmul__(self, X: torch.Tensor) -> torch.Tensor:
        if not torch.is_grad_enabled() or not X.requires_grad:
            return self.A @ X
        return _ConstantSparseMatMul.apply(X, self.A, self.At)

    def to_scipy(self) -> sp.csr_matrix:
        """A as a scipy CSR matrix (sharing the tensors' memory)."""
        return torch_to_scipy(self.A)

    @classmethod
    def from_scipy(cls, M: sp.spmatrix) -> SparseOperator:
        M = sp.csr_matrix(M)
        return cls(sparse_to_torch(M), sparse_to_torch(M.T.tocsr()))
