"""The processes that train together and must agree: an MPI communicator or a torch.distributed group.

fempdl checks that every rank makes the same decisions (the caps a layer is
called with, the metric PRDP steps on). Those checks run over whichever group
trains together:

* the mesh's MPI communicator when the mesh is distributed (``mpirun``: the
  solves themselves are collective there);
* an initialised torch.distributed process group otherwise (``torchrun`` with
  DistributedDataParallel: every process holds the whole mesh on a
  communicator of its own, so the mesh alone sees one process, and ranks whose
  caps drift apart train on different physics while DDP keeps their
  parameters equal: nothing else would show it);
* nothing on one process.
"""
from __future__ import annotations

import math

import torch
import torch.distributed as dist

__all__ = ["Ranks", "training_ranks", "torch_group_initialised", "different_metrics_message",
           "refuse_different_metrics"]


def torch_group_initialised() -> bool:
    """Whether torch.distributed's default process group exists (``init_process_group`` was called)."""
    return dist.is_available() and dist.is_initialized()


class Ranks:
    """``size`` and ``allgather(value)`` (every rank's picklable ``value``, in rank order) over an
    ``mpi4py`` communicator or a torch.distributed ``ProcessGroup`` (``None``: the default group)."""

    def __init__(self, group, *, torch_group: bool):
        self.group, self._torch = group, torch_group

    def __repr__(self) -> str:
        if self._torch:
            name = "default" if self.group is None else "given"
            backend = dist.get_backend(self.group)
            return f"Ranks({name} torch.distributed process group, backend {backend}, size {self.size})"
        return f"Ranks(MPI communicator {self.group.Get_name()!r}, size {self.size})"

    @property
    def size(self) -> int:
        return dist.get_world_size(self.group) if self._torch else self.group.size

    @property
    def torch_group(self) -> bool:
        """Whether these are the processes of a torch.distributed group (else an MPI communicator's)."""
        return self._torch

    @property
    def kind(self) -> str:
        return "torch.distributed process group" if self._torch else "MPI communicator"

    def max(self, value: float) -> float:
        """The largest ``value`` over the ranks (over torch.distributed one all-reduce of a float, no pickling)."""
        if not self._torch:
            return max(self.group.allgather(value))
        reduced = torch.tensor([value], dtype=torch.float64)
        dist.all_reduce(reduced, op=dist.ReduceOp.MAX, group=self.group)
        return float(reduced)

    def agree(self, values: tuple) -> bool:
        """Whether every rank holds the same numbers ``values`` (``None`` entries allowed): over
        torch.distributed one all-reduce of their floats and negatives (the largest and the least are
        equal), no pickling; callers gather the values for a message only when they differ."""
        if not self._torch:
            return all(other == values for other in self.group.allgather(values))
        mine = [math.nan if v is None else float(v) for v in values]
        mine = [-math.inf if math.isnan(v) else v for v in mine]       # None: a value no cap takes
        both = torch.tensor(mine + [-v for v in mine], dtype=torch.float64)
        dist.all_reduce(both, op=dist.ReduceOp.MAX, group=self.group)
        return bool((both[:len(mine)] == -both[len(mine):]).all())

    def allgather(self, value) -> list:
        if not self._torch:
            return self.group.allgather(value)
        every = [None] * self.size
        dist.all_gather_object(every, value, group=self.group)
        return every


def training_ranks(comm=None, mesh_comm=None) -> Ranks | None:
    """The ranks that must agree, or ``None`` for one process.

    ``comm`` (an mpi4py communicator or a torch.distributed ProcessGroup) wins when given; else
    ``mesh_comm`` when it spans several processes; else the default torch.distributed group when
    one is initialised."""
    if comm is not None:
        if _is_torch_group(comm):
            return Ranks(comm, torch_group=True)
        if not hasattr(comm, "allgather") or not hasattr(comm, "size"):
            raise TypeError(f"comm must be an mpi4py communicator or a torch.distributed ProcessGroup, "
                            f"got {type(comm).__name__}")
        return Ranks(comm, torch_group=False)
    if mesh_comm is not None and mesh_comm.size > 1:
        return Ranks(mesh_comm, torch_group=False)
    if torch_group_initialised() and dist.get_world_size() > 1:
        return Ranks(None, torch_group=True)
    return None


def _is_torch_group(comm) -> bool:
    return dist.is_available() and isinstance(comm, dist.ProcessGroup)


def different_metrics_message(every: list, ranks: Ranks) -> str:
    """The refusal of PRDP steps made with different metrics on the ranks (``every``: by rank)."""
    reduce = ("torch.distributed.all_reduce(total) on the sums and counts the metric is made of" if ranks.torch_group
              else "comm.allreduce(error_sum) / comm.allreduce(count)")
    return (f"PRDP.step got different metrics on the {ranks.size} ranks ({every}) of its {ranks.kind}; every rank "
            "must step with the same metric, or one rank refines K alone (the collective solves of a distributed "
            f"mesh hang; data-parallel ranks train on different physics): reduce it first, e.g. {reduce}")


def refuse_different_metrics(ranks: Ranks | None, metric: float) -> None:
    """Raise on every rank of an MPI communicator whose ranks step PRDP with different metrics.

    Over a torch.distributed group nothing is checked here: validating and stepping on rank 0 alone is a
    common DDP pattern, and a collective here would wait for ranks that never come while they wait in
    DDP's all-reduce (a hang); the layers check at their next training call, collective under DDP anyway.
    """
    if ranks is None or ranks.size == 1 or ranks.torch_group or ranks.agree((metric,)):
        return
    every = ranks.allgather(metric)
    if any(m != metric for m in every):
        raise ValueError(different_metrics_message(every, ranks))
