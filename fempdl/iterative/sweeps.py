"""Fused Richardson sweeps on torch CSR matrices: X <- c + M X for whole (n, B) blocks.

Richardson with a diagonal preconditioner P (D^-1 for Jacobi, or I) and damping
omega, X <- X + omega P (R - A X), is the sweep X <- c + M X with

    M = I - omega P A,   c = omega P R.

One fused sparse product per sweep (read X and c, write the next iterate into a
second buffer) is the least memory traffic such a sweep can have
(``benchmarks/bench_floor.py``). Columns run in groups of about :data:`fempdl.core.tuning.SWEEP_GROUP`
per thread so that a group's iterates stay in cache, and small products run on
one torch thread (waking a second one per product costs more than it saves).
"""
from __future__ import annotations

import contextlib

import numpy as np
import scipy.sparse as sp
import torch

from fempdl.core import tuning

__all__ = ["sweep_matrix", "richardson", "column_groups", "torch_threads", "threads_for", "FIXED_POINT_CHECK"]

#: Sweeps between two checks for a fixed point in :func:`richardson` (each check reads a group's two
#: iterates once, about 1/30 of a sweep's traffic spread over this many sweeps).
FIXED_POINT_CHECK = 32


def sweep_matrix(S: sp.csr_matrix, omega: float, dinv: np.ndarray | None) -> sp.csr_matrix:
    """M = I - omega P S (scipy CSR, sorted indices) for P = diag(dinv) (n,), or I when ``dinv`` is None."""
    scale = omega * (np.ones(S.shape[0]) if dinv is None else dinv)
    M = (sp.identity(S.shape[0], format="csr") - sp.diags(scale) @ S).tocsr()
    M.sort_indices()
    return M


def column_groups(batch: int, size: int = tuning.SWEEP_GROUP) -> list[tuple[int, int]]:
    """(start, width) of about ``size`` columns each, equal widths: a group's iterates stay
    in cache, at the price of reading the matrix once per group."""
    width = -(-batch // -(-batch // size))
    return [(i, min(width, batch - i)) for i in range(0, batch, width)]


@contextlib.contextmanager
def torch_threads(count: int | None):
    """torch's intra-op threads set to ``count`` inside the block (None: unchanged)."""
    before = torch.get_num_threads()
    if count is None or count == before:
        yield
        return
    torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(before)


def threads_for(nnz: int, width: int) -> int | None:
    """1 when a sparse product of ``nnz`` entries on ``width`` columns is too small to share, else None."""
    return 1 if nnz * width < tuning.PARALLEL_MIN_WORK else None


def richardson(M: torch.Tensor, c: torch.Tensor, K: int, X0: torch.Tensor | None = None) -> torch.Tensor:
    """K sweeps X <- c + M X from X0 (or 0) for c (n, B), column group by column group; returns X (n, B).

    A group has :data:`fempdl.core.tuning.SWEEP_GROUP` columns per torch thread (each thread's rows of the
    group's iterates stay in its cache). No autograd: two buffers per group, nothing kept. Every
    :data:`FIXED_POINT_CHECK` sweeps the new iterate is compared with the last: once a sweep leaves a
    group exactly where it was (a zero residual, or a converged iterate that rounds onto itself), every
    later sweep would too, and the group stops there with the iterate K sweeps give (what PETSc's
    KSPRICHARDSON computes in all K iterations, which it runs and counts)."""
    threads = torch.get_num_threads()
    if threads_for(M.values().numel(), min(c.shape[1], tuning.SWEEP_GROUP * threads)) == 1:
        threads = 1
    groups = column_groups(c.shape[1], tuning.SWEEP_GROUP * threads)
    with torch.no_grad(), torch_threads(threads):
        out = []
        for i, width in groups:
            cg = c[:, i:i + width].contiguous()
            X = torch.zeros_like(cg) if X0 is None else X0[:, i:i + width].clone(memory_format=torch.contiguous_format)
            Y = torch.empty_like(cg)
            for k in range(K):
                torch.addmm(cg, M, X, out=Y)
                if k % FIXED_POINT_CHECK == FIXED_POINT_CHECK - 1 and torch.equal(X, Y):
                    break                       # a fixed point: every later sweep gives Y again
                X, Y = Y, X
            out.append(X)
        return out[0] if len(out) == 1 else torch.cat(out, dim=1)
