"""K steps of preconditioned CG on a constant operator, with a hand-written reverse pass.

The forward pass runs the recurrences of :mod:`fempdl.iterative.unrolled`'s CG
(PETSc's KSPCG) without autograd, per step k:

    w = A p,  gamma = p.w,  a = beta / gamma,  X' = X + a p,  r' = r - a w,
    z' = P r',  beta' = r'.z',  b = beta' / beta,  p' = z' + b p,

from r = R, p = z = P R, beta = R.P R, X = 0 (columns of (n, B) blocks; P the
inverse diagonal (n, 1), or None for the identity; a step length is 0 once the
column is solved, as in the autograd version). The reverse pass is the
vector-Jacobian product of that map, step by step backwards, with adjoints
(r^, p^, beta^) and X^ = G throughout (X only accumulates):

    b^ = p'^.p,            p^ = b p'^ + a G + gamma^ w + A^T w^,
    beta'^ += b^ / beta,   beta^ = -b^ b / beta + a^ / gamma,
    r^ = r'^ + P (p'^ + 2 beta'^ r'),
    a^ = G.p - r^.w,       gamma^ = -a^ a / gamma,
    w^ = -a r^ + gamma^ p

(beta' / beta^2 written as b / beta and beta / gamma^2 as a / gamma: no square
can overflow or underflow),

and finally R^ = r^ + P p^ + 2 beta^ P R. A step keeps p, w and r' (three
(n, B) blocks) where autograd keeps four and allocates about twice as many
temporaries; the reverse pass allocates nothing per step. With ``segment`` < K
only the segments' starting (r, p, beta) are kept, and each segment is
recomputed once in the reverse pass.
"""
from __future__ import annotations

import torch

from fempdl.iterative.columns import column_dots, guarded_ratio, spmm_into

__all__ = ["ConstantOperatorCG"]


def _precondition(P: torch.Tensor | None, v: torch.Tensor) -> torch.Tensor:
    return v if P is None else P * v


def _forward_step(A, P, r, p, beta, floor, buf, zbuf, out=None):
    """One CG step from (r, p, beta); returns (a, r', p', beta') and the step's tape.

    Writes only the blocks the tape keeps (w, r', p'), into ``out`` (three (n, B)
    blocks) or new ones; ``buf`` and ``zbuf`` are scratch."""
    w, r_new, p_new = out if out is not None else (torch.empty_like(p) for _ in range(3))
    solved = beta.abs() <= floor
    spmm_into(A, p, w)
    gamma = column_dots(p, w, buf)
    still_a = ~(solved | (gamma == 0))                     # where a = beta / gamma, else a = 0
    a = guarded_ratio(beta, gamma, ~still_a)
    torch.addcmul(r, w, a, value=-1.0, out=r_new)
    z = r_new if P is None else torch.mul(P, r_new, out=zbuf)
    beta_new = column_dots(r_new, z, buf)
    still_b = ~(solved | (beta_new.abs() <= floor) | (beta == 0))   # where b = beta' / beta
    b = guarded_ratio(beta_new, beta, ~still_b)
    torch.addcmul(z, p, b, out=p_new)
    return (a, r_new, p_new, beta_new), (p, w, r_new, beta, gamma, a, b, still_a, still_b)


def _reverse_step(At, P, G, tape, r_bar, p_bar, beta_bar, buf, spare):
    """Adjoints of (r, p, beta) before a step from those after it (X's adjoint is G).

    In place: ``r_bar`` becomes the new r^, ``spare`` the new p^ (the old ``p_bar``
    is the next step's spare); ``buf`` is scratch. Returns (r^, p^, beta^, spare)."""
    p, w, r_new, beta, gamma, a, b, still_a, still_b = tape
    b_bar = column_dots(p_bar, p, buf)
    beta_new_bar = beta_bar + guarded_ratio(b_bar, beta, ~still_b)
    beta_prev_bar = -guarded_ratio(b_bar * b, beta, ~still_b)
    torch.addcmul(p_bar, r_new, 2.0 * beta_new_bar, out=buf)
    if P is not None:
        buf.mul_(P)
    r_bar.add_(buf)                                             # r^ = r'^ + P (p'^ + 2 beta'^ r')
    a_bar = column_dots(G, p, buf) - column_dots(r_bar, w, buf)
    beta_prev_bar = beta_prev_bar + guarded_ratio(a_bar, gamma, ~still_a)
    gamma_bar = -guarded_ratio(a_bar * a, gamma, ~still_a)
    torch.mul(p, gamma_bar, out=buf).addcmul_(r_bar, a, value=-1.0)              # w^
    spmm_into(At, buf, spare)                                                     # A^T w^
    spare.addcmul_(p_bar, b).addcmul_(G, a).addcmul_(w, gamma_bar)
    return r_bar, spare, beta_prev_bar, p_bar


class ConstantOperatorCG(torch.autograd.Function):
    """X_K (n, B) of K CG steps for R (n, B) on constant torch CSR A (its transpose At),
    checkpointed every ``segment`` steps (segment >= K: every step's tape kept;
    ``keep=False``: none, for a solve nothing will differentiate).

    The kept blocks go through ``save_for_backward`` (saved-tensor hooks see them);
    the per-column scalars are attributes. Steps whose tapes are not kept, and
    recomputed segments, write into blocks reused from step to step. A backward
    pass that builds a graph (``create_graph=True``) runs ``steps(R)``, the same
    map in differentiable torch operations, instead, so that derivatives of any
    order are right."""

    @staticmethod
    def forward(ctx, R, A, At, P, K: int, segment: int, solved_fraction: float, keep: bool, steps):
        keep_all = keep and segment >= K
        with torch.no_grad():
            r, p = R, _precondition(P, R)
            beta = (r * p).sum(0)
            floor = solved_fraction * beta.abs()
            X = torch.zeros_like(R)
            buf, zbuf = torch.empty_like(R), torch.empty_like(R)
            ring = None if keep_all else [[torch.empty_like(R) for _ in range(3)] for _ in range(2)]
            blocks, scalars = [], []
            for k in range(K):
                if keep and not keep_all and k % segment == 0:
                    blocks += [r.clone(), p.clone()]      # the ring's blocks are overwritten later
                    scalars.append(beta)
                (a, r, p, beta), tape = _forward_step(A, P, r, p, beta, floor, buf, zbuf,
                                                      None if keep_all else ring[k % 2])
                X.addcmul_(tape[0], a)
                if keep_all:
                    blocks += tape[:3]                    # p_k is the previous step's p'
                    scalars.append(tape[3:])
        ctx.A, ctx.At, ctx.P, ctx.K, ctx.segment = A, At, P, K, segment
        ctx.floor, ctx.scalars, ctx.steps = floor, scalars, steps
        ctx.save_for_backward(R, *blocks)
        return X

    @staticmethod
    def backward(ctx, G):
        R, *blocks = ctx.saved_tensors
        if torch.is_grad_enabled():                       # create_graph=True
            X = ctx.steps(R)
            return torch.autograd.grad(X, R, G, create_graph=True)[0], None, None, None, None, None, None, None, None
        A, At, P, K, segment = ctx.A, ctx.At, ctx.P, ctx.K, ctx.segment
        G = G.contiguous()
        r_bar, p_bar, spare = torch.zeros_like(G), torch.zeros_like(G), torch.empty_like(G)
        buf, zbuf = torch.empty_like(G), torch.empty_like(G)
        beta_bar = torch.zeros(G.shape[1], dtype=G.dtype)
        if segment >= K:                                  # every tape kept
            segments = [[(*blocks[3 * k:3 * k + 3], *ctx.scalars[k]) for k in range(K)]]
        else:
            segments = range(len(ctx.scalars))
            pool = [[torch.empty_like(G) for _ in range(3)] for _ in range(segment)]
        for tapes in reversed(segments):
            if isinstance(tapes, int):                    # recompute segment j's tapes from its start
                j = tapes
                r, p, beta = blocks[2 * j], blocks[2 * j + 1], ctx.scalars[j]
                tapes = []
                for i in range(min(segment, K - j * segment)):
                    (_, r, p, beta), tape = _forward_step(A, P, r, p, beta, ctx.floor, buf, zbuf, pool[i])
                    tapes.append(tape)
            for tape in reversed(tapes):
                r_bar, p_bar, beta_bar, spare = _reverse_step(At, P, G, tape, r_bar, p_bar, beta_bar, buf, spare)
        del segments, tapes, spare, buf, zbuf
        if segment < K:
            del pool
        # R^ = r^ + P (p^ + 2 beta^ R), in place
        p_bar.addcmul_(R, 2.0 * beta_bar)
        if P is not None:
            p_bar.mul_(P)
        return r_bar.add_(p_bar), None, None, None, None, None, None, None, None
