"""Under mpirun -n 2: both ranks write one XDMF file from their own (COMM_SELF) meshes; rank 1 starts while
rank 0 holds the file. Each rank writes what happened to rank<r>.txt beside the file."""
import sys
from pathlib import Path

from mpi4py import MPI
import torch

from fempdl import forms, io, mesh
from fempdl.core.io import one_writer

comm = MPI.COMM_WORLD
path = Path(sys.argv[1])
problem = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.3), controls=("f",))
u = torch.ones(problem.output_size, dtype=torch.float64)
if comm.rank == 0:
    with one_writer(path.with_suffix(".xdmf"), MPI.COMM_SELF):      # rank 0 is writing ...
        comm.barrier()                                               # ... while rank 1 tries
        comm.barrier()
    outcome = "wrote"
else:
    comm.barrier()
    try:
        io.write_fields(path, problem, {"u": u})
        outcome = "wrote"
    except ValueError as err:
        outcome = str(err)
    comm.barrier()
(path.parent / f"rank{comm.rank}.txt").write_text(outcome)
