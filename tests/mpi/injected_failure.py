"""Run under mpirun -n 2: rank 1 raises while rank 0 waits in a collective.
With fempdl.core.parallel.abort_on_error the job must end (non-zero), not hang."""
from mpi4py import MPI

from fempdl.core.parallel import abort_on_error

abort_on_error()
comm = MPI.COMM_WORLD
comm.barrier()
if comm.rank == 1:
    raise RuntimeError("injected failure on rank 1")
comm.barrier()   # rank 0 waits here for a rank that will never come
print("unreachable: rank 0 passed the barrier")
