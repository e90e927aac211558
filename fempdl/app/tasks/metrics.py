"""The tasks' error measures: normalised mean squared errors, per sample and over a batch."""
from __future__ import annotations

from mpi4py import MPI
import torch

from fempdl.core import parallel

__all__ = ["nmse", "sample_nmse"]


def sample_nmse(u: torch.Tensor, ref: torch.Tensor, comm: MPI.Comm = MPI.COMM_SELF) -> torch.Tensor:
    """Per sample ||u_i - ref_i||^2 / ||ref_i||^2 for (B, n) rows, shape (B,).

    On a mesh distributed over ``comm`` the rows hold each rank's owned DOFs
    and the norms sum over all ranks (differentiably)."""
    sums = torch.stack([((u - ref) ** 2).sum(-1), (ref ** 2).sum(-1)])
    error, scale = parallel.allreduce_sum(sums, comm)
    return error / scale


def nmse(u: torch.Tensor, ref: torch.Tensor, comm: MPI.Comm = MPI.COMM_SELF) -> torch.Tensor:
    """Normalised MSE, PRDP paper eq. 56: mean_i ||u_i - ref_i||^2 / ||ref_i||^2."""
    return sample_nmse(u, ref, comm).mean()
