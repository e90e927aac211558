"""``NonlinearSolveLayer(diff="unrolled")``: the exact derivative of the Newton map that was run.

Forward: plain Newton from u_0 (zero or the warm start, boundary values put in),

    u_{k+1} = u_k - a * delta_k,   J(u_k; m) delta_k = F(u_k; m),   k = 0 ... N-1,

keeping every iterate (N + 1 vectors per sample). Backward, from u_bar = dJ/du_N
(BC entries zeroed), per step k = N-1 ... 0: mu = J(u_k)^{-T} u_bar, then
u_bar <- u_bar + a dQ/du and m_bar += a dQ/dm with Q = mu^T J(u_k; m) delta_k -
F(u_k, mu; m) (:meth:`NonlinearSystem.unrolled_adjoint`). This is the
vector-Jacobian product of the N-step map itself, so a capped Newton solve has
an exact gradient too; it needs the exact step (a direct or converged inner
solve) and the plain Newton method, whose step length does not depend on a
line search's choices.

Shapes: as the layer's (controls (B, n_m) or shared (n_m,), output (B, n)).
"""
from __future__ import annotations

import time

import numpy as np
import torch

from fempdl.layer.implicit_diff import FirstOrderOnly, count_on_all_ranks, nonfinite_control_message
from fempdl.solve.linear_system import INITIAL_GUESS

__all__ = ["UnrolledNewton", "check_unrolled_newton", "stored_values"]


def check_unrolled_newton(options) -> None:
    """Raise ValueError unless ``options`` (NewtonOptions) describe a map the unrolled pass differentiates."""
    if not options.plain:
        raise ValueError(f"diff='unrolled' differentiates plain Newton steps (snes_type='newton', or 'newtonls' with "
                         f"linesearch='basic'), not {options.snes_type!r} with its line search's or trust region's "
                         "choices; use diff='implicit' for those")
    if options.ksp.capped and not options.ksp.direct:
        raise ValueError("diff='unrolled' needs the exact Newton step: a direct or converged inner solve, not "
                         f"one capped at {options.ksp.max_it} iterations; use ksp='lu' or a converged KSPOptions, "
                         "or diff='implicit'")


def stored_values(options, batch: int, n: int) -> int:
    """The floats one call's iterates take at most: (steps + 1) * batch * n."""
    return (options.step_limit + 1) * batch * n


class UnrolledNewton(torch.autograd.Function):
    """``UnrolledNewton.apply(layer, names, batch, *tensors)`` -> U (batch, n) float64 on the CPU."""

    @staticmethod
    def forward(ctx, layer, names: tuple, batch: int, *tensors):
        t0 = time.perf_counter()
        for name, t in zip(names, tensors):
            bad = count_on_all_ranks(~torch.isfinite(t), layer.problem)
            if bad:
                raise ValueError(nonfinite_control_message(name, bad))
            layer.problem.check_control_values(name, t)
        arrays = {n: np.broadcast_to(t.numpy(), (batch, t.shape[-1])) for n, t in zip(names, tensors)}
        guess = arrays.pop(INITIAL_GUESS, None)
        U, path = layer.solve_healthy(
            lambda health: layer.system.solve(arrays, batch, initial_guess=guess, record=True, health=health),
            training=any(ctx.needs_input_grad[3:]))
        ctx.state = layer.call_state.pack(layer.system)        # the caps the kept solve ran at
        ctx.layer, ctx.names, ctx.path = layer, names, path
        ctx.shared = [t.dim() == 1 for t in tensors]
        ctx.save_for_backward(*tensors)
        layer.stats.layer_time += time.perf_counter() - t0
        return torch.from_numpy(U)

    @staticmethod
    def backward(ctx, grad_out):
        needs = ctx.needs_input_grad[3:]
        wanted = [n for n, need in zip(ctx.names, needs) if need]
        if not wanted:
            return (None,) * (3 + len(ctx.names))
        layer = ctx.layer
        t0 = time.perf_counter()
        tensors = ctx.saved_tensors
        G = grad_out.detach().to(dtype=torch.float64).numpy()
        bad = count_on_all_ranks(~np.isfinite(G), layer.problem)
        if bad:
            raise ValueError(f"the gradient flowing back into NonlinearSolveLayer contains {bad} NaN/inf value(s); "
                             "the loss or the layers after this one produced them")
        batch = G.shape[0]
        arrays = {n: np.broadcast_to(t.detach().numpy(), (batch, t.shape[-1]))
                  for n, t in zip(ctx.names, tensors) if n != INITIAL_GUESS}
        with layer.call_state.restored(layer.system, ctx.state):   # the Constants the forward read
            grads = layer.system.unrolled_adjoint(arrays, ctx.path, G, [n for n in wanted if n != INITIAL_GUESS],
                                                  initial_guess=INITIAL_GUESS in wanted)
        result = []
        for name, shared in zip(ctx.names, ctx.shared):
            g = grads.get(name)
            if g is not None:
                g = torch.from_numpy(g.sum(0) if shared else g)
            result.append(g)
        if torch.is_grad_enabled():
            anchors = [t for t in (*tensors, grad_out) if t.requires_grad]
            if anchors:
                result = [None if g is None else FirstOrderOnly.apply(g, layer.second_derivative_message, *anchors)
                          for g in result]
        layer.stats.layer_time += time.perf_counter() - t0
        return (None, None, None) + tuple(result)
