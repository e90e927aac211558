"""Under mpirun -n 2: one data-parallel step with and without parallel.sum_gradients, and ranks
started from different seeds; rank 0 prints what parallel.check_same_parameters said on both ranks."""
from mpi4py import MPI
import torch

from fempdl.core import parallel

comm = MPI.COMM_WORLD


def one_step(sum_gradients: bool, seed: int = 0) -> str:
    """One SGD step on this rank's own samples; the parameter check's verdict, the same on every rank."""
    torch.manual_seed(seed)
    model = torch.nn.Linear(3, 1)
    optimizer = torch.optim.SGD(model.parameters(), lr=0.1)
    inputs = torch.randn(4, 3, generator=torch.Generator().manual_seed(100 + comm.rank))   # this rank's shard
    model(inputs).square().mean().backward()
    if sum_gradients:
        parallel.sum_gradients(model.parameters(), comm)
    optimizer.step()
    try:
        parallel.check_same_parameters(model, comm)
        verdict = "same"
    except ValueError as err:
        verdict = f"ValueError: {err}"
    verdicts = comm.allgather(verdict)
    if len(set(verdicts)) != 1:
        return f"the ranks disagree: {verdicts}"
    kind, _, message = verdict.partition(": ")
    return f"{kind} on both ranks" + (f": {message}" if message else "")


results = {"summed": one_step(True), "forgotten": one_step(False), "seeds": one_step(True, seed=comm.rank)}
if comm.rank == 0:
    for key, value in results.items():
        print(f"{key}: {value}")
