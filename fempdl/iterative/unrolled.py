"""K-step iterative solvers as differentiable torch maps (unrolled differentiation).

:func:`solve` runs exactly K iterations from X_0 = 0 for all columns of a
right-hand-side block R (n, B) at once, with torch operations only, so that
autograd through it gives the exact vector-Jacobian product of the K-step
iterate (not of the converged solution). Methods:

* ``"jacobi"`` — Richardson with Jacobi (or no) preconditioning and damping
  omega: X <- X + omega P (R - A X); the iterate of PETSc's KSPRICHARDSON +
  PCJACOBI/PCNONE with ``ksp_richardson_scale`` omega.
* ``"steepest_descent"`` — the PRDP paper's Algorithm 2: r = R - A X,
  alpha = (r.r) / (r.A r), X <- X + alpha r (unpreconditioned).
* ``"cg"`` — preconditioned CG with the recurrences of PETSc's KSPCG, the
  iterate of KSPCG + PCJACOBI/PCNONE.
* ``"gmres"`` — left-preconditioned GMRES(m) with classical Gram-Schmidt and
  restarts, the iterate of KSPGMRES (see :func:`gmres`).

A is a constant :class:`fempdl.iterative.sparse.SparseOperator` (or anything with ``@``), P the
inverse diagonal (n, 1) or None.
No 0/0 can occur: when a column's residual vanishes (a zero right-hand side),
or has fallen by 1e-20 from its start (far past double precision), its step
lengths are 0 and the column stays where it is; forward values and gradients
stay finite. Up to that point the iterate is PETSc's.

On a constant operator (right-hand-side controls) Richardson runs as fused
sweeps whose adjoint is K transposed sweeps, and CG with a hand-written
reverse pass (:mod:`fempdl.iterative.reverse_cg`); a matrix control goes
through autograd, step by step.

Memory: the backward pass needs ``stored_values`` floats (a few K n B). With
``max_values`` set below that, the iterations run in segments of about
sqrt(K) iterations that keep only their starting state in the forward pass
and are recomputed one at a time during the backward pass, so about 2 sqrt(K)
states are stored instead of K (``checkpointed_values``, which must then fit
in ``max_values``; recomputation is exact: the iteration is deterministic). A
solve whose stored values would exceed the memory budget
(:func:`fempdl.core.resources.memory_budget`, half the available memory) is
refused before it starts, with the estimate and the ways out.
"""
from __future__ import annotations

import copy
import math
import weakref

import torch

from fempdl.core.resources import format_bytes, memory_budget
from fempdl.iterative import sweeps
from fempdl.iterative.columns import SOLVED, guarded_ratio
from fempdl.iterative.reverse_cg import ConstantOperatorCG
from fempdl.iterative.sparse import SparseOperator, sparse_to_torch

__all__ = ["solve", "METHODS", "stored_values", "checkpointed_values"]


class _Jacobi:
    def init(self, A, P, R, omega):
        return (torch.zeros_like(R),)

    def step(self, A, P, R, omega, state):
        (X,) = state
        return (X + omega * (R - A @ X),)


class _SteepestDescent:
    def init(self, A, P, R, omega):
        return (torch.zeros_like(R), R)

    def step(self, A, P, R, omega, state):
        X, r = state
        Ar = A @ r
        rr = (r * r).sum(0)
        alpha = guarded_ratio(rr, (r * Ar).sum(0), rr <= SOLVED * (R * R).sum(0).detach())
        return (X + alpha * r, r - alpha * Ar)


class _ConjugateGradient:
    # State (X, r, p, beta = r.z, floor): a column counts as solved once r.z has fallen below
    # floor = 1e-40 |r0.z0| (1e-20 in the preconditioned residual norm), as the batched engine's CG.
    def init(self, A, P, R, omega):
        z = R if P is None else P * R
        beta = (R * z).sum(0)
        return (torch.zeros_like(R), R, z, beta, SOLVED * beta.detach().abs())

    def step(self, A, P, R, omega, state):
        X, r, p, beta, floor = state
        solved = beta.detach().abs() <= floor
        w = A @ p
        a = guarded_ratio(beta, (p * w).sum(0), solved)
        X = X + a * p
        r = r - a * w
        z = r if P is None else P * r
        beta_new = (r * z).sum(0)
        p = z + guarded_ratio(beta_new, beta, solved | (beta_new.detach().abs() <= floor)) * p
        return (X, r, p, beta_new, floor)


METHODS = {"jacobi": _Jacobi(), "steepest_descent": _SteepestDescent(), "cg": _ConjugateGradient()}


def gmres(A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int, restart: int) -> torch.Tensor:
    """K iterations of left-preconditioned GMRES(restart) with classical Gram-Schmidt
    (PETSc's KSPGMRES defaults), from X = 0; a cycle cut short by K ends with the
    least-squares update of its partial basis, as PETSc does.

    Happy breakdown (the Krylov space of a column became invariant: the new
    basis vector's norm fell below 1e-14 of the cycle's residual) makes that
    column exact: its later basis vectors are zero and its Hessenberg matrix is
    padded with unit columns on fresh rows, which keeps the small least-squares
    problem of full rank (its padded coefficients are 0) and the gradients finite.
    """
    n, batch = R.shape
    X = torch.zeros_like(R)
    done = 0
    while done < K:
        steps = min(restart, K - done)
        r = R - A @ X
        r = r if P is None else P * r
        beta = r.norm(dim=0)
        broken = beta == 0                                          # nothing left to solve
        basis = [r / torch.where(broken, torch.ones_like(beta), beta)]
        columns = []
        for j in range(steps):
            w = A @ basis[j]
            w = w if P is None else P * w
            # Classical Gram-Schmidt, one basis vector at a time: stacking the
            # basis would give autograd a new (j + 1, n, B) copy to keep per step.
            h = torch.stack([(v * w).sum(0) for v in basis])       # (j + 1, B)
            w = w - sum(v * h[k] for k, v in enumerate(basis))
            h_next = w.norm(dim=0)
            newly = ~broken & (h_next <= 1e-14 * beta)
            pad = broken                                            # broken before this step
            broken = broken | newly
            column = torch.zeros(steps + 1, batch, dtype=R.dtype)
            column = column + torch.nn.functional.pad(torch.where(pad, torch.zeros_like(h), h),
                                                      (0, 0, 0, steps - j))
            unit = torch.zeros(steps + 1, batch, dtype=R.dtype)
            unit[j + 1] = 1.0
            sub = torch.where(broken, torch.zeros_like(h_next), h_next)
            column = column + unit * torch.where(pad, torch.ones_like(sub), sub)
            columns.append(column)
            basis.append(torch.where(broken, torch.zeros_like(w),
                                     w / torch.where(broken, torch.ones_like(h_next), h_next)))
        H = torch.stack(columns, dim=1).permute(2, 0, 1)            # (B, steps + 1, steps)
        rhs = torch.zeros(batch, steps + 1, 1, dtype=R.dtype)
        rhs = rhs + torch.nn.functional.pad(beta[:, None, None], (0, 0, 0, steps))
        Q, T = torch.linalg.qr(H)
        y = torch.linalg.solve_triangular(T, Q.transpose(1, 2) @ rhs, upper=True)[..., 0]   # (B, steps)
        X = X + sum(basis[k] * y[:, k] for k in range(steps))
        done += steps
    return X


# Floats kept for the backward pass per iteration, in units of n * B, with a constant
# operator and with one whose entries are differentiated (a matrix control), counted
# with saved-tensor hooks. With a constant operator Jacobi keeps nothing (its map is
# linear: _LinearRichardson) and CG three blocks (fempdl.iterative.reverse_cg).
_STORED_PER_ITERATION = {"jacobi": (0, 2), "steepest_descent": (2, 2), "cg": (3, 4), "gmres": (4, 5)}


def stored_values(method: str, K: int, n: int, batch: int, *, matrix_grad: bool = False) -> int:
    """Float values autograd keeps for a K-step solve of ``batch`` columns of size n
    (``matrix_grad``: the operator's entries require grad)."""
    if method not in _STORED_PER_ITERATION:
        raise ValueError(f"method must be one of {sorted(_STORED_PER_ITERATION)}, got {method!r}")
    return _STORED_PER_ITERATION[method][int(matrix_grad)] * K * n * batch


# Vectors (n, B) in a method's state: what a checkpointed segment keeps at its start.
_STATE_VECTORS = {"jacobi": 1, "steepest_descent": 2, "cg": 3}


def _segment_length(K: int) -> int:
    return max(1, int(math.sqrt(K)))


# (n, B) work blocks a backward pass holds besides the stored iterates (CG's reverse pass:
# the adjoints of r and p, a spare, two scratch blocks and the gradient).
_WORK_BLOCKS = 6


def checkpointed_values(method: str, K: int, n: int, batch: int, *, matrix_grad: bool = False) -> int:
    """Float values a checkpointed K-step solve keeps at most: the starting state of every segment plus,
    during the backward pass, one segment's stored iterates and the pass's work blocks."""
    segment = _segment_length(K)
    starts = math.ceil(K / segment) * _STATE_VECTORS[method] * n * batch
    return starts + stored_values(method, segment, n, batch, matrix_grad=matrix_grad) + _WORK_BLOCKS * n * batch


class _LinearRichardson(torch.autograd.Function):
    """X_K = sum_{j<K} M^j c for c = scale R: K sweeps X <- c + M X, M = I - scale A.

    The map is linear in R, so its vector-Jacobian product is K sweeps with M^T,
    scaled: scale sum_{j<K} (M^T)^j G. Nothing per iteration is kept, and the
    backward costs what the forward does."""

    @staticmethod
    def forward(ctx, R, M, Mt, scale, K):
        ctx.M, ctx.Mt, ctx.scale, ctx.K = M, Mt, scale, K
        return sweeps.richardson(M, R * scale, K)

    @staticmethod
    def backward(ctx, G):
        # The adjoint is the same kind of map (M^T for M), so derivatives of any order follow.
        return ctx.scale * _LinearRichardson.apply(G, ctx.Mt, ctx.M, 1.0, ctx.K), None, None, None, None


# SparseOperator -> (P, omega, M, M^T): the sweep matrices of a constant operator, for its latest P and omega.
_SWEEP_MATRICES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _sweep_pair(A: SparseOperator, P: torch.Tensor | None, omega: float) -> tuple:
    """(M, M^T) as torch CSR for M = I - omega P A, rebuilt when P (by identity) or omega change."""
    kept = _SWEEP_MATRICES.get(A)
    if kept is None or kept[0] is not P or kept[1] != omega:
        M = sweeps.sweep_matrix(A.to_scipy(), omega, None if P is None else P[:, 0].numpy())
        kept = (P, omega, sparse_to_torch(M), sparse_to_torch(M.T.tocsr()))
        _SWEEP_MATRICES[A] = kept
    return kept[2:]


class _Segment(torch.autograd.Function):
    """``run(state, extras)`` computed without a graph; recomputed with one in the backward pass.

    Only the inputs are kept: the segment's starting state and the ``extras``,
    the operands that need gradients (right-hand side, preconditioner, matrix
    entries). The recomputation runs on detached copies of all of them, so it
    never reaches into the graph outside the segment."""

    @staticmethod
    def forward(ctx, run, n_state: int, *tensors):
        ctx.run, ctx.n_state = run, n_state
        ctx.save_for_backward(*tensors)
        with torch.no_grad():
            return tuple(run(tensors[:n_state], tensors[n_state:]))

    @staticmethod
    def backward(ctx, *grads):
        inputs = [t.detach().requires_grad_(t.requires_grad) for t in ctx.saved_tensors]
        with torch.enable_grad():
            out = ctx.run(inputs[:ctx.n_state], inputs[ctx.n_state:])
        used = [(o, g) for o, g in zip(out, grads) if g is not None and o.requires_grad]
        wanted = [t for t in inputs if t.requires_grad]
        found = iter(torch.autograd.grad([o for o, _ in used], wanted, [g for _, g in used], allow_unused=True)
                     if used and wanted else [None] * len(wanted))
        return (None, None, *[next(found) if t.requires_grad else None for t in inputs])


def _check_bound(method: str, K: int, R: torch.Tensor, matrix_grad: bool, max_values: int) -> None:
    """Refuse a solve that would keep more than ``max_values`` floats even when checkpointed."""
    n, batch = R.shape
    least = checkpointed_values(method, K, n, batch, matrix_grad=matrix_grad) if method in _STATE_VECTORS else None
    if least is not None and least <= max_values:
        return
    how = (f"checkpointed, it keeps at least {least} ({format_bytes(8 * least)} in float64)" if least is not None
           else f"{method} is not checkpointed and keeps {stored_values(method, K, n, batch, matrix_grad=matrix_grad)}")
    raise MemoryError(f"diff='unrolled' with {method}, K={K}, n={n}, B={batch} cannot keep within "
                      f"max_unrolled_values={max_values}: {how}; raise max_unrolled_values, pass fewer samples "
                      f"per call, or use diff='implicit' (stores nothing per iteration)")


def _check_memory(method: str, K: int, R: torch.Tensor, matrix_grad: bool, checkpointed: bool,
                  budget: int | None) -> None:
    """Refuse a solve whose stored iterates would exceed ``budget`` bytes (default: half the available memory)."""
    n, batch = R.shape
    size = R.element_size()
    plain = stored_values(method, K, n, batch, matrix_grad=matrix_grad) * size
    if method in _STATE_VECTORS:
        bounded = checkpointed_values(method, K, n, batch, matrix_grad=matrix_grad) * size
    else:
        bounded = None
    need = bounded if checkpointed and bounded is not None else plain
    budget = memory_budget() if budget is None else budget
    if need <= budget:
        return
    ways = ["diff='implicit' (stores nothing per iteration)", "fewer samples per call"]
    if bounded is not None and not checkpointed:
        ways.insert(0, f"max_unrolled_values below {plain // size} (checkpointing keeps about 2 sqrt(K) states: "
                       f"{format_bytes(bounded)})")
    raise MemoryError(f"diff='unrolled' with {method}, K={K}, n={n}, B={batch} would keep about "
                      f"{format_bytes(need)} for the backward pass, more than the memory budget of "
                      f"{format_bytes(budget)} (half the available memory); use " + ", or ".join(ways))


def solve(method: str, A: torch.Tensor, P: torch.Tensor | None, R: torch.Tensor, K: int, *,
          omega: float = 1.0, restart: int = 30, max_values: int | None = None,
          X0: torch.Tensor | None = None, memory_budget: int | None = None) -> torch.Tensor:
    """K iterations of ``method`` on A X = R (R: (n, B)) from X = 0 or from ``X0``; returns X (n, B).

    A warm start is the K-step solve of the residual equation, X0 + S_K(R - A X0),
    which is what PETSc's Krylov methods do with a nonzero initial guess; autograd
    differentiates the dependence on X0 exactly. On a constant
    :class:`~fempdl.iterative.sparse.SparseOperator` with a constant P, Richardson
    runs as fused sweeps whose adjoint is K transposed sweeps (nothing kept), and
    CG with a hand-written reverse pass (:mod:`fempdl.iterative.reverse_cg`).

    ``max_values`` bounds the floats kept for the backward pass: above it the
    iterations are checkpointed (about 2 sqrt(K) states kept, each segment
    recomputed once). GMRES is not checkpointed (its state is a whole Krylov basis).

    Raises:
        MemoryError: with gradients on, the values to keep exceed ``max_values``
            even when checkpointed, or exceed ``memory_budget`` bytes (default:
            half the available memory).
    """
    if X0 is not None:
        return X0 + solve(method, A, P, R - A @ X0, K, omega=omega, restart=restart, max_values=max_values,
                          memory_budget=memory_budget)
    if method != "gmres" and method not in METHODS:
        raise ValueError(f"method must be one of {sorted(METHODS) + ['gmres']}, got {method!r}")
    matrix_grad = bool(getattr(A, "requires_grad", False))
    # Besides the iterates, a backward pass holds R and a few work blocks.
    stored = stored_values(method, K, *R.shape, matrix_grad=matrix_grad) + (1 + _WORK_BLOCKS) * R.numel()
    checkpointed = method != "gmres" and max_values is not None and stored > max_values
    differentiated = torch.is_grad_enabled() and any(
        isinstance(t, torch.Tensor) and t.requires_grad for t in (R, P, omega, getattr(A, "values", None)))
    if differentiated:
        if max_values is not None and stored > max_values:
            _check_bound(method, K, R, matrix_grad, max_values)
        _check_memory(method, K, R, matrix_grad, checkpointed, memory_budget)
    if method == "gmres":
        return gmres(A, P, R, K, restart)
    constant = isinstance(A, SparseOperator) and not (P is not None and P.requires_grad) \
        and not isinstance(omega, torch.Tensor)
    if method == "jacobi" and constant:
        # The K-step map is linear in R, with a K-sweep adjoint.
        M, Mt = _sweep_pair(A, P, omega)
        return _LinearRichardson.apply(R, M, Mt, omega if P is None else P * omega, K)
    if method == "cg" and constant:
        return ConstantOperatorCG.apply(R, A.A, A.At, P, K, _segment_length(K) if checkpointed else K, SOLVED,
                                        differentiated, lambda R: _steps("cg", A, P, R, K, omega))
    return _steps(method, A, P, R, K, omega, checkpointed and differentiated)


def _steps(method: str, A, P, R: torch.Tensor, K: int, omega, checkpointed: bool = False) -> torch.Tensor:
    """K steps of ``method`` in differentiable torch operations (checkpointed in segments of about sqrt(K))."""
    impl = METHODS[method]
    if method == "jacobi":
        # One step tensor for all iterations: omega D^{-1}, or omega alone.
        omega = omega if P is None else P * omega
    state = impl.init(A, P, R, omega)

    def run(count, *s):
        for _ in range(count):
            s = impl.step(A, P, R, omega, s)
        return s

    if not checkpointed:
        return run(K, *state)[0]
    # The operands that need gradients pass through _Segment as inputs; an operator's
    # differentiable entries are its ``values`` (the linear layer's matrix controls).
    operands = {"R": R, "P": P, "omega": omega, "values": getattr(A, "values", None)}
    varying = [name for name, t in operands.items() if isinstance(t, torch.Tensor) and t.requires_grad]

    def segment_run(count: int, s: tuple, extras: tuple) -> tuple:
        given = {**operands, **dict(zip(varying, extras))}
        op = A
        if "values" in varying:
            op = copy.copy(A)
            op.values = given["values"]
        for _ in range(count):
            s = impl.step(op, given["P"], given["R"], given["omega"], s)
        return s

    segment, done = _segment_length(K), 0
    while done < K:
        count = min(segment, K - done)
        state = _Segment.apply(lambda s, extras, count=count: segment_run(count, s, extras), len(state), *state,
                               *[operands[name] for name in varying])
        done += count
    return state[0]
