"""``SolveLayer(diff="implicit")``: the capped solve in PETSc, differentiated by the adjoint solve.

Forward: A(m) u = b(m) by the layer's capped solver (K = ``max_it``). Backward:
A(m)^T lam = dJ/du (BC entries zeroed, same solver and cap, and the Constants,
fixed Functions and cap that the forward read: :class:`~fempdl.solve.call_state.CallState`; solved
again at a refined cap where PRDP's health check finds it garbage, :mod:`fempdl.layer.healthy_calls`), then
dJ/dm = -lam^T dF/dm for every control that requires grad, and, for a warm
start x0, the adjoint residual dJ/du - A^T lam (:meth:`LinearSystem.adjoint`).

Shapes: controls (B, n_m), or (n_m,) shared by the batch; u and dJ/du (B, n).
Both solves are opaque torch operators (``fempdl::implicit_solve``,
``fempdl::implicit_adjoint``) with fake (shape-only) kernels and vmap rules
that fold a vmapped dimension into the native batch, so torch.func
(grad, vjp, jacrev, vmap) and torch.compile see one op per solve.
"""
from __future__ import annotations

import itertools
import time
import weakref

import numpy as np
import torch
import torch._dynamo  # noqa: F401  (imported by a custom op's first call otherwise: 1-2 s inside a solve)
from torch import Tensor

from fempdl.solve.linear_system import INITIAL_GUESS

__all__ = ["ImplicitSolve", "FirstOrderOnly", "SECOND_DERIVATIVE_MESSAGE", "count_on_all_ranks", "count_nonfinite",
           "register_layer", "nonfinite_control_message"]

# Live layers by integer handle: the operators take the handle, not the layer
# (an operator's arguments are tensors and plain values).
_LAYERS: dict[int, weakref.ref] = {}
_HANDLES = itertools.count(1)


def register_layer(layer) -> int:
    """A handle under which the operators find ``layer`` (dropped when it is garbage collected)."""
    handle = next(_HANDLES)
    _LAYERS[handle] = weakref.ref(layer, lambda _, h=handle: _LAYERS.pop(h, None))
    return handle


def _layer(handle: int):
    ref = _LAYERS.get(handle)
    layer = ref() if ref is not None else None
    if layer is None:
        raise RuntimeError(f"SolveLayer handle {handle} no longer refers to a live layer")
    return layer


def nonfinite_control_message(name: str, bad: int) -> str:
    return f"control {name!r} contains {bad} NaN/inf value(s); check the upstream network or data"


# ------------------------------------------------------------------ operators
@torch.library.custom_op("fempdl::implicit_solve", mutates_args=())
def implicit_solve(handle: int, names: str, batch: int, training: bool, float32: bool,
                   tensors: list[Tensor]) -> tuple[Tensor, Tensor]:
    """U (batch, n) in float64 on the CPU, and the packed state the solve read (the layer's
    ``call_state``: a copy of its Constants and fixed Functions, small beside a solve);
    ``names`` comma-separated, one per tensor; ``training``: a backward may follow."""
    layer = _layer(handle)
    t0 = time.perf_counter()
    names = _split(names)
    values = _float64_values(names, tensors)
    for name, a in values.items():
        bad = count_nonfinite(a, layer.problem)
        if bad:
            raise ValueError(nonfinite_control_message(name, bad))
        layer.problem.check_control_values(name, a)          # a coefficient declared positive
    shared = frozenset(n for n, t in zip(names, tensors) if t.dim() == 1)
    arrays = _batched(values, batch)
    guess = arrays.pop(INITIAL_GUESS, None)
    # A training call (its backward follows: the solve keeps per-sample matrices for it) is solved again at a
    # refined cap while its capped solves are garbage; the state is packed after, so the backward runs at the
    # caps that held.
    call = layer.call_state.new_call()
    U = layer.solve_healthy(lambda health: layer.system.solve(arrays, batch, shared, initial_guess=guess,
                                                              keep_for=call if training else None,
                                                              health=health),
                            training=training)
    state = layer.call_state.pack(layer.system, call)
    if float32 and count_nonfinite(U.astype(np.float32), layer.problem):
        layer._report_overflow(torch.float32)
    layer.stats.layer_time += time.perf_counter() - t0
    # The layout register_fake promises.
    return torch.from_numpy(np.ascontiguousarray(U, dtype=np.float64)), torch.from_numpy(state)


@implicit_solve.register_fake
def _(handle, names, batch, training, float32, tensors):
    layer = _layer(handle)
    return (torch.empty((batch, layer.problem.output_size), dtype=torch.float64, device="cpu"),
            torch.empty((layer.call_state.size,), dtype=torch.float64, device="cpu"))


@torch.library.custom_op("fempdl::implicit_adjoint", mutates_args=())
def implicit_adjoint(handle: int, names: str, wanted: str, tensors: list[Tensor], u: Tensor,
                     du: Tensor, state: Tensor) -> list[Tensor]:
    """dJ/dm (batch, n_m) float64 for each name in ``wanted`` (in ``names`` order), given u and du = dJ/du
    (batch, n), with the Constants, fixed Functions and cap the forward read (``state``) put back."""
    layer = _layer(handle)
    t0 = time.perf_counter()
    names, wanted = _split(names), _split(wanted)
    G = _to_numpy(du)
    bad = count_nonfinite(G, layer.problem)
    if bad:
        raise ValueError(f"the gradient flowing back into SolveLayer contains {bad} NaN/inf "
                         "value(s); the loss or the layers after this one produced them")
    batch = G.shape[0]
    shared = frozenset(n for n, t in zip(names, tensors) if t.dim() == 1)
    arrays = _batched(_float64_values(names, tensors), batch)
    arrays.pop(INITIAL_GUESS, None)
    packed, runs = state.numpy(), itertools.count()

    def adjoint(health):
        # The forward's record; where the health check refined the caps since (a garbage adjoint), those.
        record = packed if next(runs) == 0 else layer.call_state.with_caps(packed, layer.system.caps)
        measure = {"health": health} if layer.measures_adjoint_health else {}
        with layer.call_state.restored(layer.system, record):
            return layer.system.adjoint(arrays, _to_numpy(u), G, [n for n in wanted if n != INITIAL_GUESS],
                                        shared, initial_guess=INITIAL_GUESS in wanted,
                                        kept_for=layer.call_state.call_of(packed), **measure)
    # A start that carries no gradient (detached, or a stored solution) leaves the capped map's derivative
    # short of the physics' by the adjoint's residual, however close the warm-started forward is: such an
    # adjoint is held to the approximation's limit, not the exact derivative's.
    exact = layer.exact_capped_gradient and (INITIAL_GUESS not in names or INITIAL_GUESS in wanted)
    grads = layer.solve_healthy(adjoint, training=layer.measures_adjoint_health, direction="adjoint", exact=exact)
    layer.stats.layer_time += time.perf_counter() - t0
    return [torch.from_numpy(np.ascontiguousarray(grads[n], dtype=np.float64)) for n in wanted]


@implicit_adjoint.register_fake
def _(handle, names, wanted, tensors, u, du, state):
    sizes = {n: t.shape[-1] for n, t in zip(_split(names), tensors)}
    return [torch.empty((du.shape[0], sizes[n]), dtype=torch.float64, device="cpu") for n in _split(wanted)]


def _solve_vmap(info, in_dims, handle, names, batch, training, float32, tensors):
    V, dims = info.batch_size, in_dims[5]
    if all(d is None for d in dims):
        return implicit_solve(handle, names, batch, training, float32, tensors), (None, None)
    folded = [_fold(t, d, V, batch) for t, d in zip(tensors, dims)]
    U, state = implicit_solve(handle, names, V * batch, training, float32, folded)
    return (U.reshape(V, batch, U.shape[-1]), state), (0, None)


def _adjoint_vmap(info, in_dims, handle, names, wanted, tensors, u, du, state):
    V = info.batch_size
    out_v, grad_v = _fold3(u, in_dims[4], V), _fold3(du, in_dims[5], V)
    batch = grad_v.shape[1]
    folded = [_fold(t, d, V, batch) for t, d in zip(tensors, in_dims[3])]
    if in_dims[6] is not None:       # one forward's state, seen by every vmapped sample
        state = state.select(in_dims[6], 0)
    grads = implicit_adjoint(handle, names, wanted, folded, out_v.reshape(V * batch, -1),
                             grad_v.reshape(V * batch, -1), state)
    return [g.reshape(V, batch, g.shape[-1]) for g in grads], [0] * len(grads)


implicit_solve.register_vmap(_solve_vmap)
implicit_adjoint.register_vmap(_adjoint_vmap)


def _fold(t: Tensor, dim, V: int, batch: int) -> Tensor:
    """One operand of a vmapped call as an operand of the native batch of V * batch samples.

    A tensor that is shared, (n_m,), in every vmapped sample stays shared; otherwise
    it becomes (V * batch, n_m), vmapped sample v owning rows v * batch ... (v + 1) * batch - 1."""
    if dim is None:
        if t.dim() == 1:
            return t
        return t.unsqueeze(0).expand(V, *t.shape).reshape(V * batch, t.shape[-1])
    t = t.movedim(dim, 0)
    if t.dim() == 2:   # shared within a vmapped sample, different across them
        t = t.unsqueeze(1).expand(V, batch, t.shape[-1])
    return t.reshape(V * batch, t.shape[-1])


def _fold3(t: Tensor, dim, V: int) -> Tensor:
    """A (batch, n) operand as (V, batch, n)."""
    return t.unsqueeze(0).expand(V, *t.shape) if dim is None else t.movedim(dim, 0)


# ------------------------------------------------------------------ autograd
class ImplicitSolve(torch.autograd.Function):
    """The forward solve with the adjoint solve as its backward (setup_context style, so
    torch.func transforms apply; vmap goes through the operators' vmap rules).

    ``ImplicitSolve.apply(handle, names, batch, training, float32, *tensors)`` -> (U, state):
    ``names`` a tuple with one control name per tensor, ``batch`` the native batch B, ``training`` whether
    a backward may follow (gradients are wanted); ``state`` the packed values the solve read, not
    differentiable."""

    generate_vmap_rule = True

    @staticmethod
    def forward(handle: int, names: tuple, batch: int, training: bool, float32: bool, *tensors):
        return implicit_solve(handle, ",".join(names), batch, training, float32, list(tensors))

    @staticmethod
    def setup_context(ctx, inputs, output):
        handle, names, batch, _, _, *tensors = inputs
        out, state = output
        ctx.mark_non_differentiable(state)
        # Saved through autograd so that an in-place change of an input or of the
        # output before backward raises autograd's error instead of corrupting
        # the gradient (backward re-assembles with the controls and u).
        ctx.save_for_backward(*tensors, out, state)
        ctx.handle, ctx.names = handle, names
        # The graph holds the layer alive until backward: the operators see only the
        # handle, and a layer built inline (SolveLayer(p)(f=f)) has no other owner.
        ctx.layer = _LAYERS[handle]() if handle in _LAYERS else None
        ctx.inputs = [(t.dim(), t.dtype, t.device) for t in tensors]

    @staticmethod
    def backward(ctx, grad_out, _grad_state):
        # First order: the adjoint operator gets detached operands, so under torch.func
        # it sees plain or vmapped tensors (a second derivative raises, below).
        needs = ctx.needs_input_grad[5:]
        wanted = [n for n, need in zip(ctx.names, needs) if need]
        if not wanted:
            return (None,) * (5 + len(ctx.names))
        *tensors, out, state = ctx.saved_tensors
        grads = implicit_adjoint(ctx.handle, ",".join(ctx.names), ",".join(wanted),
                                 [t.detach() for t in tensors], out.detach(), grad_out.detach(), state)
        grads = dict(zip(wanted, grads))
        result = []
        for name, (dim, dtype, device) in zip(ctx.names, ctx.inputs):
            g = grads.get(name)
            if g is not None:
                g = g.sum(0) if dim == 1 else g  # a shared (n,) control collects all samples
                g = g.to(device=device, dtype=dtype)
            result.append(g)
        if torch.is_grad_enabled():
            # create_graph=True: the gradient is first order only; differentiating it again
            # raises instead of silently dropping the layer's second-order term.
            anchors = [t for t in (*tensors, grad_out) if t.requires_grad]
            if anchors:
                message = getattr(ctx.layer, "second_derivative_message", SECOND_DERIVATIVE_MESSAGE)
                result = [None if g is None else FirstOrderOnly.apply(g, message, *anchors) for g in result]
        return (None,) * 5 + tuple(result)


SECOND_DERIVATIVE_MESSAGE = (
    "second derivatives through SolveLayer(diff='implicit') are not implemented: its backward is the "
    "first-order adjoint solve, so a Hessian-vector product or a gradient of a gradient would miss the "
    "layer's second-order term. Use diff='unrolled' (the exact derivatives of every order of the capped "
    "Richardson or CG iterate), or finite differences of the first-order gradient")


class FirstOrderOnly(torch.autograd.Function):
    """The identity on a first-order gradient whose backward raises ``message``: built into the graph when a
    backward runs with ``create_graph=True`` and tied to the tensors the gradient depends on, so
    that only an actual second derivative (not the first-order gradient itself) fails."""

    generate_vmap_rule = True

    @staticmethod
    def forward(grad, message: str, *anchors):
        return grad.clone()

    @staticmethod
    def setup_context(ctx, inputs, output):
        ctx.message = inputs[1]

    @staticmethod
    def backward(ctx, _):
        raise RuntimeError(ctx.message)


# ------------------------------------------------------------------ helpers
def count_on_all_ranks(mask, problem) -> int:
    """Number of True entries over all ranks: every rank must take the same branch
    (raise, or go on into collective solves)."""
    comm = problem.V.mesh.comm
    count = int(mask.sum())
    return comm.allreduce(count) if comm.size > 1 else count


def count_nonfinite(values: np.ndarray, problem) -> int:
    """Number of NaN/inf entries of ``values`` over all ranks, as :func:`count_on_all_ranks`; one
    pass over a finite array (the usual case), the count only when there is something to report."""
    local = np.isfinite(values).all()
    return count_on_all_ranks(np.array(0) if local else ~np.isfinite(values), problem)


def _split(names: str) -> list[str]:
    return names.split(",") if names else []


def _float64_values(names, tensors) -> dict:
    """float64 arrays per control, (B, n_m) or (n_m,); a tensor passed for two names (a time
    step's state as control and as initial guess) is converted once."""
    converted, values = {}, {}
    for n, t in zip(names, tensors):
        if id(t) not in converted:
            converted[id(t)] = _to_numpy(t)
        values[n] = converted[id(t)]
    return values


def _batched(values: dict, batch: int) -> dict:
    """(batch, n_m) arrays per control: shared (n_m,) controls as broadcast views."""
    return {n: a if a.ndim == 2 else np.broadcast_to(a, (batch, a.shape[-1])) for n, a in values.items()}


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).numpy()
