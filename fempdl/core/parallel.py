"""MPI process-group helpers: aborting a failed job, and the reductions of parallel training.

:func:`abort_on_error` makes an uncaught exception on any rank end the whole
job. Without it a failing rank exits through ``MPI_Finalize`` (mpi4py's exit
hook), which waits for the other ranks, while they wait in their next
collective for the failed one: the job hangs. With it the failing rank prints
its traceback (prefixed with its rank) and calls ``MPI_Abort``, and mpirun ends
every rank with a non-zero exit. ``fempdl`` installs it whenever it runs on
more than one rank; scripts can call it themselves, or run as
``mpirun -n P python -m mpi4py script.py``, which does the same.

Parallel training (:class:`fempdl.app.runs.training.Trainer`) has two modes:

* ``"data"``: every rank holds the whole problem (a mesh on ``COMM_SELF``) and
  the same model; a batch is cut into one contiguous :func:`shard` per rank,
  each rank's loss is weighted by its share of the batch and
  :func:`sum_gradients` adds the ranks' gradients, so every rank applies the
  serial batch gradient (up to the order of the float additions).
* ``"mesh"``: the mesh is distributed over the ranks and the model's
  parameters are replicated. Sums over DOFs go through :func:`allreduce_sum`,
  which is differentiable; each rank's backward then reaches the parameters
  only through its own DOFs, and :func:`sum_gradients` adds those parts.

:func:`check_identical` is the guard of both: values every rank must agree on
(the iteration cap K, the validation metric) are compared after every epoch,
and a mismatch is an error, not a silent drift. :func:`check_same_parameters`
does the same for the model's parameters (the Trainer calls it every epoch; a
loop of your own calls it too): a loop that forgets :func:`sum_gradients`
trains a different model on each rank, and nothing else would notice.
"""
from __future__ import annotations

import os
import sys
import traceback

from mpi4py import MPI
import numpy as np
import torch

from fempdl.core.checks import is_int, is_real

__all__ = ["abort_on_error", "allreduce_sum", "check_identical", "check_same_parameters", "fit_threads",
           "parameter_fingerprint", "shard", "sum_gradients"]


def fit_threads(threads: int | None = None, comm: MPI.Comm = MPI.COMM_WORLD) -> int:
    """Set torch's threads: ``threads``, or this node's cores shared among its ranks.

    Every rank of an mpirun starts as many threads as the node has cores, so P
    ranks on P cores oversubscribe them P-fold; this gives each rank
    cores // (ranks on its node), at least 1. Returns the number set."""
    if threads is None:
        node = comm.Split_type(MPI.COMM_TYPE_SHARED)
        local_ranks = node.size
        node.Free()
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        threads = max(1, cores // local_ranks) if local_ranks > 1 else torch.get_num_threads()
    if not is_int(threads) or threads < 1:
        raise ValueError(f"threads must be an int >= 1, got {threads!r}")
    threads = int(threads)
    torch.set_num_threads(threads)
    return threads


def abort_on_error(comm: MPI.Comm = MPI.COMM_WORLD, exit_code: int = 1) -> None:
    """Install an exception hook that aborts ``comm`` on an uncaught exception (if it has > 1 rank)."""
    if comm.size == 1:
        return
    previous = sys.excepthook

    def hook(kind, value, tb):
        if issubclass(kind, KeyboardInterrupt):  # Ctrl-C: mpirun already signals every rank
            previous(kind, value, tb)
            return
        text = "".join(traceback.format_exception(kind, value, tb))
        sys.stderr.write("".join(f"[rank {comm.rank}] {line}\n" for line in text.rstrip().splitlines()))
        sys.stderr.write(f"[rank {comm.rank}] aborting all {comm.size} ranks\n")
        sys.stderr.flush()
        comm.Abort(exit_code)

    sys.excepthook = hook


def shard(indices: torch.Tensor, comm: MPI.Comm) -> torch.Tensor:
    """This rank's contiguous part of ``indices``; the parts' sizes differ by at most one (some may be empty)."""
    bounds = np.linspace(0, len(indices), comm.size + 1).round().astype(int)
    return indices[bounds[comm.rank]:bounds[comm.rank + 1]]


def batch_size(inputs: dict[str, torch.Tensor]) -> int:
    """The samples in a call's keyword inputs: the leading size of its (B, n) tensors, 1 when every
    input is a shared (n,) tensor. Raises ValueError when the batched ones disagree."""
    sizes = {name: value.shape[0] for name, value in inputs.items() if value.dim() == 2}
    if len(set(sizes.values())) > 1:
        raise ValueError(f"inputs have different batch sizes {sizes}; pass (B, n) tensors with one B, or (n,) "
                         "tensors shared by all samples")
    return next(iter(sizes.values()), 1)


def shard_inputs(inputs: dict[str, torch.Tensor], comm: MPI.Comm) -> dict[str, torch.Tensor]:
    """This rank's :func:`shard` of a call's keyword inputs: the (B, n) ones are split along B, the
    shared (n,) ones kept whole; when nothing is batched, the call is one sample, as (1, n)."""
    if not any(value.dim() == 2 for value in inputs.values()):
        inputs = {name: value[None] for name, value in inputs.items()}
    idx = shard(torch.arange(batch_size(inputs)), comm)
    return {name: value[idx] if value.dim() == 2 else value for name, value in inputs.items()}


def sum_gradients(parameters, comm: MPI.Comm) -> None:
    """Replace every parameter's ``.grad`` by its sum over the ranks of ``comm`` (one Allreduce).

    A rank that has no gradient for a parameter (it had no samples) adds zeros;
    a parameter that has none on any rank keeps ``grad = None``, as in a serial
    step, so the optimizer skips it there too. The sum is taken in float64.
    """
    parameters = [p for p in parameters if p.requires_grad]
    has = np.array([p.grad is not None for p in parameters], dtype=np.int32)
    comm.Allreduce(MPI.IN_PLACE, has, op=MPI.MAX)
    active = [p for p, flag in zip(parameters, has) if flag]
    if not active:
        return
    flat = torch.cat([(p.grad if p.grad is not None else torch.zeros_like(p)).detach().reshape(-1).double()
                      for p in active]).numpy()
    comm.Allreduce(MPI.IN_PLACE, flat, op=MPI.SUM)
    offset = 0
    for p in active:
        p.grad = torch.from_numpy(flat[offset:offset + p.numel()]).reshape(p.shape).to(p.dtype).clone()
        offset += p.numel()


class _AllreduceSum(torch.autograd.Function):
    # The sum is replicated, and what every rank computes from it is the same
    # loss, counted once: d loss / d (this rank's part) = d loss / d (sum), so
    # the backward passes the gradient through unchanged.
    @staticmethod
    def forward(ctx, local, comm):
        total = local.detach().numpy().copy()
        comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        return torch.from_numpy(total)

    @staticmethod
    def backward(ctx, grad):
        return grad, None


def allreduce_sum(local: torch.Tensor, comm: MPI.Comm) -> torch.Tensor:
    """The sum of ``local`` over the ranks of ``comm``, differentiable (CPU tensors, same shape on every rank).

    Use it only where every rank goes on to compute the same loss from the
    result (see the module docstring); the identity on one rank."""
    if comm.size == 1:
        return local
    return _AllreduceSum.apply(local, comm)


def _same(a, b) -> bool:
    return a == b or (a != a and b != b)   # NaN on every rank is agreement


def check_identical(comm: MPI.Comm, **values) -> None:
    """Raise ``RuntimeError`` naming the values that are not equal on every rank of ``comm``."""
    if comm.size == 1:
        return
    gathered = comm.allgather(values)
    differing = [name for name in values if any(not _same(other[name], values[name]) for other in gathered)]
    if differing:
        listing = "; ".join(f"{name}: " + ", ".join(f"rank {r}: {g[name]!r}" for r, g in enumerate(gathered))
                            for name in differing)
        raise RuntimeError(f"parallel training went out of step ({listing}); the ranks must agree on these")


def parameter_fingerprint(parameters) -> np.ndarray:
    """(T, 3) float64 for T parameter tensors: each one's sum, sum of squares and size, the sums by
    numpy's pairwise summation, whose result depends only on the values (not on torch's threads)."""
    rows = []
    for p in parameters:
        values = p.detach().cpu().double().numpy().reshape(-1)
        rows.append((values.sum(), np.dot(values, values), values.size))
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def check_same_parameters(model, comm: MPI.Comm = MPI.COMM_WORLD, *, rtol: float = 0.0) -> None:
    """Raise ValueError on every rank of ``comm`` unless the ranks hold the same parameters.

    Call it in a parallel training loop (every epoch, say): a loop that forgets
    :func:`sum_gradients` after ``backward`` trains a different model on each rank,
    silently. One allgather of a fingerprint (:func:`parameter_fingerprint`) per call.

    Ranks that start from the same parameters and apply the summed gradients hold the same
    bits: :func:`sum_gradients` hands every rank the same float64 sums (an MPI sum of the same
    numbers in the same order on every rank), and the optimizer's step is the same elementwise
    arithmetic on each. So the default compares exactly; ``rtol`` > 0 allows that relative gap
    (of each tensor's sum and sum of squares) for an MPI whose sums differ by rank in the last bits.

    Args:
        model: a ``torch.nn.Module`` (its parameters are named in the error) or an iterable of tensors.
    """
    if not is_real(rtol) or not 0.0 <= rtol < 1.0:
        raise ValueError(f"rtol must be a number in [0, 1), got {rtol!r}")
    if isinstance(model, torch.nn.Module):
        named = list(model.named_parameters())
        names, parameters = [name for name, _ in named], [p for _, p in named]
    else:
        parameters = tuple(model)
        names = tuple(f"parameter {i}" for i in range(len(parameters)))
    if comm.size == 1:
        return
    every = comm.allgather(parameter_fingerprint(parameters))
    if any(f.shape != every[0].shape for f in every):
        raise ValueError(f"the ranks hold models of different sizes ({[len(f) for f in every]} parameter tensors, "
                         "by rank); build the same model on every rank")
    differ, gap = _differing(np.stack(every), rtol)
    if len(differ):
        first = differ[0]
        sums = ", ".join(f"rank {r}: {f[first, 0]!r}" for r, f in enumerate(every))
        raise ValueError(
            f"the ranks hold different parameters: {len(differ)} of {len(parameters)} tensors differ, e.g. "
            f"{names[first]!r} sums to {sums} (relative gap {gap[first]:.3g}); every rank must apply the same "
            "update: call parallel.sum_gradients(model.parameters(), comm) after loss.backward() and before "
            "optimizer.step(), and start every rank from the same parameters (the same torch.manual_seed)")


def _differing(stacked: np.ndarray, rtol: float) -> tuple:
    """Indices of the tensors whose fingerprints (ranks, T, 3) differ by more than ``rtol`` over the
    ranks (NaN on every rank is agreement, as in :func:`check_identical`), and each tensor's relative gap."""
    nan = np.isnan(stacked)
    equal = (stacked == stacked[0]).all(axis=0) | nan.all(axis=0)
    with np.errstate(invalid="ignore"):
        gap = stacked.max(axis=0) - stacked.min(axis=0)
        scale = np.abs(stacked).max(axis=0)
        relative = np.where(scale > 0, gap / np.where(scale > 0, scale, 1.0), 0.0)
        close = ~nan.any(axis=0) & (relative <= rtol)
    differ = np.flatnonzero(~(equal | close).all(axis=1))
    return differ, np.nan_to_num(relative, nan=np.inf).max(axis=1)
