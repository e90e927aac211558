"""``SolveLayer(diff="implicit")``: the capped solve in PETSc, differentiated by the adjoint solve.

Forward: A(m) u = b(m) by the layer's capped solver (K = ``max_it``). Backward:
A(m)^T lam = dJ/du (BC entries zeroed, same solver and cap), then
dJ/dm = -lam^T dF/dm for every control that requires grad, and, for a warm
start x0, the adjoint residual dJ/du - A^T lam (:meth:`LinearSystem.adjoint`).
"""
from __future__ import annotations

import time

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from fempdl.system import INITIAL_GUESS

__all__ = ["ImplicitSolve", "count_on_all_ranks"]


class ImplicitSolve(torch.autograd.Function):
    """autograd.Function around the layer's LinearSystem; all non-tensor state lives in the layer."""

    @staticmethod
    def forward(ctx, layer, names: tuple, batch: int, *tensors):
        t0 = time.perf_counter()
        shared = frozenset(n for n, t in zip(names, tensors) if t.dim() == 1)
        arrays = _batched_arrays(names, tensors, batch)
        guess = arrays.pop(INITIAL_GUESS, None)
        U = layer.system.solve(arrays, batch, shared, initial_guess=guess,
                               keep_matrices=any(ctx.needs_input_grad[3:]))
        out = torch.from_numpy(U)
        # Saved through autograd so that an in-place change of an input or of the
        # output before backward raises autograd's error instead of corrupting
        # the gradient (backward re-assembles with the controls and u).
        ctx.save_for_backward(*tensors, out)
        ctx.layer, ctx.names, ctx.batch, ctx.shared = layer, names, batch, shared
        ctx.inputs = [(t.shape, t.dtype, t.device) for t in tensors]
        layer.stats.layer_time += time.perf_counter() - t0
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        t0 = time.perf_counter()
        layer, names = ctx.layer, ctx.names
        wanted = [n for n, need in zip(names, ctx.needs_input_grad[3:]) if need]
        grads = {}
        if wanted:
            G = _to_numpy(grad_out)
            bad = count_on_all_ranks(~np.isfinite(G), layer.problem)
            if bad:
                raise ValueError(f"the gradient flowing back into SolveLayer contains {bad} NaN/inf "
                                 "value(s); the loss or the layers after this one produced them")
            *tensors, out = ctx.saved_tensors
            arrays = _batched_arrays(names, tensors, ctx.batch)
            arrays.pop(INITIAL_GUESS, None)
            grads = layer.system.adjoint(arrays, out.numpy(), G, [n for n in wanted if n != INITIAL_GUESS],
                                         ctx.shared, initial_guess=INITIAL_GUESS in wanted)
        out = []
        for name, (shape, dtype, device) in zip(names, ctx.inputs):
            g = grads.get(name)
            if g is None:
                out.append(None)
                continue
            g = torch.from_numpy(g)
            g = g.sum(0) if len(shape) == 1 else g  # a shared (n,) control collects all samples
            out.append(g.to(device=device, dtype=dtype))
        layer.stats.layer_time += time.perf_counter() - t0
        return (None, None, None, *out)


def count_on_all_ranks(mask, problem) -> int:
    """Number of True entries over all ranks: every rank must take the same branch
    (raise, or go on into collective solves)."""
    return problem.V.mesh.comm.allreduce(int(mask.sum()))


def _batched_arrays(names, tensors, batch: int) -> dict:
    """float64 arrays (batch, n_m) per control; shared (n_m,) controls as broadcast views."""
    return {n: np.broadcast_to(_to_numpy(t), (batch, t.shape[-1])) for n, t in zip(names, tensors)}


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).numpy()
