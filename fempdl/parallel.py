"""MPI process-group helpers.

:func:`abort_on_error` makes an uncaught exception on any rank end the whole
job. Without it a failing rank exits through ``MPI_Finalize`` (mpi4py's exit
hook), which waits for the other ranks, while they wait in their next
collective for the failed one: the job hangs. With it the failing rank prints
its traceback (prefixed with its rank) and calls ``MPI_Abort``, and mpirun ends
every rank with a non-zero exit. ``fempdl`` installs it whenever it runs on
more than one rank; scripts can call it themselves, or run as
``mpirun -n P python -m mpi4py script.py``, which does the same.
"""
from __future__ import annotations

import sys
import traceback

from mpi4py import MPI

__all__ = ["abort_on_error"]


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
