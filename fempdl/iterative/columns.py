"""Per-column operations on (n, B) blocks, and a sparse product into a given block:
what the batched and the unrolled iterations share.

In the unrolled (differentiable) iterations a column counts as solved once its
preconditioned residual product r.z has fallen below :data:`SOLVED` times its
start (1e-20 in the norm, far past double precision): its step lengths are then
0, so that no 0/0 occurs and squared norms never underflow into overflowing
derivatives. The batched engine's CG, which has no derivatives to guard, stops
where PETSc's KSPCG stops instead (:mod:`fempdl.iterative.batched_cg`).
"""
from __future__ import annotations

import torch

__all__ = ["SOLVED", "guarded_ratio", "column_dots", "spmm_into"]

SOLVED = 1e-40


def guarded_ratio(num: torch.Tensor, den: torch.Tensor, zero: torch.Tensor | None = None) -> torch.Tensor:
    """num / den per column, 0 where den == 0 or ``zero`` is set (finite values and gradients)."""
    zero = den == 0 if zero is None else (den == 0) | zero
    return torch.where(zero, torch.zeros_like(num), num / torch.where(zero, torch.ones_like(den), den))


def column_dots(X: torch.Tensor, Y: torch.Tensor, buf: torch.Tensor) -> torch.Tensor:
    """sum_i X[i, b] Y[i, b] for every column b, through the scratch block ``buf`` (n, B).

    Multiply into scratch, then sum: faster inside the CG loops than torch.linalg.vecdot."""
    return torch.mul(X, Y, out=buf).sum(0)


def spmm_into(A: torch.Tensor, X: torch.Tensor, out: torch.Tensor) -> torch.Tensor:
    """out = A @ X for a torch CSR A; ``A @ X`` would zero-fill a new result and copy it once more."""
    return torch.addmm(out, A, X, beta=0.0, out=out)
