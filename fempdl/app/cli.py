"""The ``fempdl`` command.

``fempdl run [SCENE]`` trains a scene with PRDP (or a fixed ``--k``, or the
converged cap) and, unless ``--no-baseline``, with the converged baseline too,
then prints the K schedule, final metric, inner iterations and wall time of
each; under ``mpirun -n P`` it needs ``--parallel data`` (every batch spread
over the ranks) or ``--parallel mesh`` (the mesh distributed over them). On a
sip or hig scene it trains the scene's method (SIP, HIG) and Adam with
backpropagation. ``fempdl tradeoff SCENE`` sweeps fixed caps, runs the
baseline and PRDP, and writes a table, plots and the IC/PR savings split.
``fempdl compare SCENE`` runs a sip or hig scene's method and Adam with
backpropagation side by side, at equal iterations and at equal training time,
and writes the ratios and plots of the error against both. ``fempdl scenes``
lists the bundled scenes; ``fempdl scenes --show NAME`` prints one's TOML,
``fempdl scenes --schema`` every section and key a scene file takes.
``--set section.key=value`` (repeatable) overrides a scene value, checked
like the file. ``fempdl run --save-fields`` writes each run's validation
predictions, references and errors (``fields.xdmf``, ``fields.png``).

A command locks its output directory while it runs (a second command on it
is refused) and refuses a directory that holds an earlier run unless told
``--resume`` (continue it; a changed scene, setting, ``--k``, mode or
baseline is refused, naming what changed) or ``--overwrite`` (replace it),
and a directory holding files fempdl did not write unless told
``--overwrite`` (files of the names fempdl writes are replaced, nothing
else is deleted), also with ``--resume``.
"""
from __future__ import annotations

import argparse
import os
import resource
import sys
from pathlib import Path

from fempdl import __version__

__all__ = ["main", "build_parser", "positive_int", "thread_count", "DEFAULT_SCENE"]

DEFAULT_SCENE = "heat-emulator-2d"
OVERWRITE_HELP = ("replace the runs already in --out, or write into a directory holding other files "
                  "(files of the names fempdl writes are replaced; nothing else is deleted)")


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def thread_count(text: str) -> int:
    """Torch threads: 1 up to the cores this process may run on. More only take turns on the same
    cores, and torch's OpenMP threads spin while they wait, so a run slows down instead of speeding
    up; far more (--threads 100000) exhaust the process limit and fail deep inside MPI or gmsh."""
    value = positive_int(text)
    cores = usable_cores()
    if value > cores:
        raise argparse.ArgumentTypeError(f"must be at most {cores}, the cores this process may run on, got "
                                         f"{value}; more threads than cores slow torch down")
    return value


def usable_cores() -> int:
    """The CPUs this process may run on (its affinity: under mpirun's binding, its rank's share)."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def seed_int(text: str) -> int:
    """A seed: a whole number in [0, 2^63 - 1] (what torch's and numpy's generators take)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if not 0 <= value < 2 ** 63:
        raise argparse.ArgumentTypeError(f"must be in [0, 2^63 - 1], got {value}")
    return value


def _k_list(text: str) -> list[int]:
    values = sorted({positive_int(part) for part in text.split(",") if part.strip()})
    if not values:
        raise argparse.ArgumentTypeError(f"expected comma-separated ints >= 1, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fempdl", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"fempdl {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="train a scene (default: heat-emulator-2d with PRDP)")
    run.add_argument("scene", nargs="?", default=DEFAULT_SCENE, help="bundled scene name or path to a .toml file")
    mode = run.add_mutually_exclusive_group()
    mode.add_argument("--k", type=positive_int, help="train with a fixed iteration cap K")
    mode.add_argument("--prdp", action="store_true", help="train with PRDP (the default)")
    mode.add_argument("--converged", action="store_true", help="train with the converged cap K_eps only")
    run.add_argument("--out", type=Path, help="output directory (default runs/SCENE)")
    run.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    run.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    run.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    run.add_argument("--no-baseline", action="store_true", help="skip the converged baseline run")
    run.add_argument("--no-progress", action="store_true", help="hide progress bars")
    run.add_argument("--seed", type=seed_int, help="network initialisation and minibatch order (default: the "
                                              "scene's data seed; the data stay the scene's)")
    run.add_argument("--tensorboard", action="store_true",
                     help="also write each run's metrics as TensorBoard scalars into RUN/tensorboard "
                          "(needs pip install 'fempdl[tensorboard]')")
    run.add_argument("--save-fields", action="store_true",
                     help="after training, write the first four validation samples' predictions, references "
                          "and errors to fields.xdmf (ParaView; one time step per sample) and, on a 2D mesh on "
                          "one process, the first's to fields.png, in each run's directory")
    run.add_argument("--parallel", choices=("data", "mesh"),
                     help="under mpirun: spread every batch over the ranks (data) or distribute the mesh (mesh)")

    trade = sub.add_parser("tradeoff", help="sweep fixed K, the converged baseline and PRDP; table and plots")
    trade.add_argument("scene", help="bundled scene name or path to a .toml file")
    trade.add_argument("--ks", type=_k_list, help="fixed caps to sweep (default 1, 2, 4, ... below K_eps)")
    trade.add_argument("--out", type=Path, help="output directory (default runs/SCENE/tradeoff)")
    trade.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    trade.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    trade.add_argument("--no-progress", action="store_true")

    comp = sub.add_parser("compare", help="a sip or hig scene's method against Adam + backprop; ratios and plots")
    comp.add_argument("scene", help="bundled scene name or path to a .toml file (task sip or hig)")
    comp.add_argument("--out", type=Path, help="output directory (default runs/SCENE/compare)")
    comp.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    comp.add_argument("--equal-iterations-only", action="store_true",
                      help="do not extend the baseline to the method's training time")
    comp.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    comp.add_argument("--overwrite", action="store_true", help=OVERWRITE_HELP)
    comp.add_argument("--no-progress", action="store_true")

    for command in (run, trade, comp):
        command.add_argument("--threads", type=thread_count,
                             help="torch threads per process, at most the cores it may run on (default: "
                                  "torch's; under mpirun the node's cores shared among its ranks)")
        command.add_argument("--log-every", type=positive_int, metavar="N",
                             help="log a line every N epochs to stderr (default: every epoch when stderr "
                                  "is not a terminal, none on a terminal, where the progress bar shows)")
        command.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                             help="override a scene value (repeatable), e.g. --set optimizer.epochs=5 "
                                  "--set solver.preset=cg; VALUE is a TOML value or plain text (a string), "
                                  "checked like the file")

    scenes = sub.add_parser("scenes", help="list the bundled scenes, print one, or print the schema")
    shown = scenes.add_mutually_exclusive_group()
    shown.add_argument("--show", metavar="NAME", help="print bundled scene NAME's TOML (a start for your own)")
    shown.add_argument("--schema", action="store_true",
                       help="print every section and key of a scene file: type, default, allowed values, meaning")
    return parser


def main(argv=None) -> int:
    """Parse ``argv`` (default: the command line) and run the command; returns the exit code."""
    args = build_parser().parse_args(argv)
    _start_mpi_under_a_file_size_limit()
    # Imported once the arguments are parsed, so that --help and argument errors answer without
    # loading MPI, DOLFINx and torch (seconds): commands.py, in cli's room, imports them all.
    from fempdl.app.commands import execute
    return execute(args)


def _start_mpi_under_a_file_size_limit() -> None:
    """Let MPI start on one process (no mpirun) under a file size limit (``ulimit -f``): Open MPI's
    PMIx keeps its data in a shared-memory file of about 4 MiB, and beyond the limit its start fails
    ("PMIX ERROR ... gds_ds21_lock_pthread.c") before fempdl can say anything. Its hash store keeps
    the data in memory. A file of the run beyond the limit then fails to be written (Python ignores
    SIGXFSZ, so the write fails with EFBIG) and the command says which one. Under mpirun, the
    launcher has chosen already."""
    limited = resource.getrlimit(resource.RLIMIT_FSIZE)[0] != resource.RLIM_INFINITY
    launched = any(name in os.environ for name in ("OMPI_COMM_WORLD_SIZE", "PMIX_RANK", "PMI_RANK"))
    if limited and not launched:
        os.environ.setdefault("PMIX_MCA_gds", "hash")


if __name__ == "__main__":
    sys.exit(main())
