"""Under mpirun -n 2: an unrolled Newton call on a distributed mesh whose iterates cannot fit in memory,
and a kappa control with values <= 0 on one rank only; rank 0 prints what every rank raised."""
from mpi4py import MPI  # before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads
import dolfinx.mesh
import numpy as np
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, forms

comm = MPI.COMM_WORLD
prob = forms.nonlinear_diffusion.problem(dolfinx.mesh.create_unit_square(comm, 8, 8), controls=("f", "kappa"))
f = torch.ones(prob.control_size("f"), dtype=torch.float64)


def verdict(call) -> str:
    """What ``call`` raised, the same on every rank (or the ranks' differing answers)."""
    try:
        call()
        mine = "nothing"
    except (MemoryError, ValueError) as err:
        mine = f"{type(err).__name__}: {err}"
    every = comm.allgather(mine)
    return every[0] if len(set(every)) == 1 else f"the ranks disagree: {every}"


huge = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=10**8), diff="unrolled")
kappa = np.ones(prob.control_size("kappa"))
if comm.rank == 1:
    kappa[:2] = -1.0                               # the values a rank's shard of a raw network output may hold
results = {"budget": verdict(lambda: huge(f=f)), "steps": comm.allreduce(huge.stats.newton_steps),
           "kappa": verdict(lambda: prob.check_control_values("kappa", kappa))}
if comm.rank == 0:
    for key, value in results.items():
        print(f"{key}: {value}")
