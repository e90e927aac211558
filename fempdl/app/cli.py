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
``--resume`` (continue it; a changed scene or setting is refused, naming
what changed) or ``--overwrite`` (replace it).
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import sys
from pathlib import Path

from mpi4py import MPI

from fempdl import __version__, parallel
from fempdl.app import compare, rundir, runner, scene, tradeoff
from fempdl.app.checkpoints import CheckpointError, remove_stale_temporaries
from fempdl.app.scene import METHOD_TASKS
from fempdl.app.training import CHECKPOINT

DEFAULT_SCENE = "heat-emulator-2d"


def positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
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
    run.add_argument("--overwrite", action="store_true", help="replace the runs already in --out")
    run.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    run.add_argument("--no-baseline", action="store_true", help="skip the converged baseline run")
    run.add_argument("--no-progress", action="store_true", help="hide progress bars")
    run.add_argument("--seed", type=int, help="network initialisation and minibatch order (default: the "
                                              "scene's data seed; the data stay the scene's)")
    run.add_argument("--tensorboard", action="store_true",
                     help="also write each run's metrics as TensorBoard scalars into RUN/tensorboard "
                          "(needs pip install 'fempdl[tensorboard]')")
    run.add_argument("--save-fields", action="store_true",
                     help="after training, write validation predictions, references and errors to "
                          "fields.xdmf (ParaView) and fields.png in each run's directory")
    run.add_argument("--parallel", choices=("data", "mesh"),
                     help="under mpirun: spread every batch over the ranks (data) or distribute the mesh (mesh)")

    trade = sub.add_parser("tradeoff", help="sweep fixed K, the converged baseline and PRDP; table and plots")
    trade.add_argument("scene", help="bundled scene name or path to a .toml file")
    trade.add_argument("--ks", type=_k_list, help="fixed caps to sweep (default 1, 2, 4, ... below K_eps)")
    trade.add_argument("--out", type=Path, help="output directory (default runs/SCENE/tradeoff)")
    trade.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    trade.add_argument("--overwrite", action="store_true", help="replace the runs already in --out")
    trade.add_argument("--no-progress", action="store_true")

    comp = sub.add_parser("compare", help="a sip or hig scene's method against Adam + backprop; ratios and plots")
    comp.add_argument("scene", help="bundled scene name or path to a .toml file (task sip or hig)")
    comp.add_argument("--out", type=Path, help="output directory (default runs/SCENE/compare)")
    comp.add_argument("--epochs", type=positive_int, help="override the scene's number of epochs")
    comp.add_argument("--equal-iterations-only", action="store_true",
                      help="do not extend the baseline to the method's training time")
    comp.add_argument("--resume", action="store_true", help="continue from the checkpoints in --out")
    comp.add_argument("--overwrite", action="store_true", help="replace the runs already in --out")
    comp.add_argument("--no-progress", action="store_true")

    for command in (run, trade, comp):
        command.add_argument("--threads", type=positive_int,
                             help="torch threads per process (default: torch's; under mpirun the node's "
                                  "cores shared among its ranks)")
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
    args = build_parser().parse_args(argv)
    parallel.abort_on_error()  # under mpirun: one rank's error ends the job, never a hang
    if args.command != "scenes":
        parallel.fit_threads(args.threads)
    if args.command != "scenes" and getattr(args, "parallel", None) is None and MPI.COMM_WORLD.size > 1:
        # Without a mode every rank would train the same run and write the same files.
        print(f"fempdl: running on {MPI.COMM_WORLD.size} ranks needs `fempdl run SCENE --parallel data|mesh`",
              file=sys.stderr)
        return 2

    if args.command == "scenes":
        return _scenes(args)
    with _library_log(getattr(args, "log_every", None), MPI.COMM_WORLD.rank):
        return _load_and_run(args)


def _scenes(args) -> int:
    """``fempdl scenes``: the bundled scenes, one's TOML (``--show``) or the schema (``--schema``)."""
    if args.schema:
        print(scene.schema_text())
        return 0
    if args.show is not None:
        try:
            print(scene.bundled_text(args.show), end="")
        except scene.SceneError as err:
            print(f"fempdl: {err}", file=sys.stderr)
            return 2
        return 0
    for name in scene.available():
        print(f"{name:<22} {scene.load(name).description}")
    return 0


def _load_and_run(args) -> int:
    try:
        sc = scene.load(args.scene, args.set)
    except (scene.SceneError, FileNotFoundError) as err:
        print(f"fempdl: {err}", file=sys.stderr)
        return 2
    if args.epochs is not None:
        sc = dataclasses.replace(sc, optimizer=dataclasses.replace(sc.optimizer, epochs=args.epochs))
    try:
        out = _output_directory(args, sc)
        # The whole command holds the lock: a second command on the same --out is refused,
        # not only a second run in one of its subdirectories.
        with rundir.RunLock(out) if MPI.COMM_WORLD.rank == 0 else contextlib.nullcontext():
            if MPI.COMM_WORLD.rank == 0:
                remove_stale_temporaries(out)       # of reports a killed command was writing
            return _command(args, sc, out)
    except (rundir.RunDirectoryError, rundir.ResumeError, CheckpointError) as err:
        if MPI.COMM_WORLD.size > 1:
            raise      # the other ranks are in a collective call: abort_on_error ends them all
        print(f"fempdl: {err}", file=sys.stderr)
        return 2


@contextlib.contextmanager
def _library_log(every: int | None, rank: int):
    """Show the "fempdl" logger's messages on stderr while a command runs: its INFO
    lines (epochs, PRDP refinements, K_eps) when stderr is not a terminal or
    ``--log-every`` is given, only warnings otherwise and on ranks other than 0.
    Epoch lines are kept every ``every`` epochs."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(logging.Formatter("fempdl: %(message)s"))
    show = rank == 0 and (every is not None or not sys.stderr.isatty())
    handler.setLevel(logging.INFO if show else logging.WARNING)
    every = every or 1
    handler.addFilter(lambda record: getattr(record, "epoch", 0) % every == 0)
    logger = logging.getLogger("fempdl")
    level, propagate = logger.level, logger.propagate
    logger.addHandler(handler)
    logger.setLevel(min(level or logging.WARNING, logging.INFO))
    # Not also through the root logger: importing dolfinx installs a stderr handler there,
    # which would print every line a second time.
    logger.propagate = False
    try:
        yield
    finally:
        logger.removeHandler(handler)
        logger.setLevel(level)
        logger.propagate = propagate


def _output_directory(args, sc) -> Path:
    """--out, or runs/<scene name>[/tradeoff|/compare]; refused (RunDirectoryError) when it holds a run
    that neither --resume nor --overwrite says what to do with."""
    default = rundir.child(Path("runs"), sc.name, "scene name")
    out = args.out or {"run": default, "tradeoff": default / "tradeoff", "compare": default / "compare"}[args.command]
    resume = getattr(args, "resume", False)
    if resume and args.overwrite:
        raise rundir.RunDirectoryError("--resume and --overwrite contradict each other: give one")
    if not (resume or args.overwrite) and rundir.holds_run(out):
        raise rundir.RunDirectoryError(f"{str(out)!r} holds the files of an earlier run; pass --resume to continue "
                                       "it, --overwrite to replace it, or choose another --out")
    return out


def _command(args, sc, out: Path) -> int:
    """The run, tradeoff or compare command of a loaded scene, into ``out``."""
    progress = not args.no_progress and sys.stderr.isatty()
    if (args.command == "compare") != (sc.task in METHOD_TASKS) and args.command != "run":
        use = "fempdl compare" if sc.task in METHOD_TASKS else "fempdl tradeoff"
        print(f"fempdl: `fempdl {args.command}` does not apply to the {sc.task} scene {sc.name!r}; use `{use}`",
              file=sys.stderr)
        return 2
    if sc.task in METHOD_TASKS:
        return _methods(args, sc, progress, out)
    if args.command == "tradeoff":
        runs = tradeoff.sweep(sc, ks=args.ks, out_dir=out, progress=progress)
        split = tradeoff.savings(runs, stop_at=sc.optimizer.stop_at)
        paths = tradeoff.write_report(sc, runs, split, out)
        print(tradeoff.comparison_table(runs))
        print("\n".join(tradeoff.summary_lines(split)))
        print("wrote " + ", ".join(str(p) for p in paths))
        return 0

    try:
        runner.check_parallel(sc, args.parallel)
    except ValueError as err:
        print(f"fempdl: {err}", file=sys.stderr)
        return 2
    if args.save_fields and (sc.task not in runner.FIELD_TASKS or args.parallel == "mesh"):
        print(f"fempdl: --save-fields writes the fields of {' and '.join(runner.FIELD_TASKS)} scenes, "
              f"serial or with --parallel data; {sc.name!r} is of task {sc.task!r}"
              + (" on a distributed mesh" if args.parallel == "mesh" else ""), file=sys.stderr)
        return 2
    runs = {}
    baseline = None
    common = {"progress": progress, "parallel": args.parallel, "seed": args.seed, "save": args.save_fields,
              "tensorboard": args.tensorboard}
    if not args.no_baseline or args.converged:
        baseline = runner.run(sc, "converged", out_dir=out / "converged",
                                   resume=_can_resume(args, out / "converged"), **common)
    if not args.converged:
        mode, k, label = ("fixed", args.k, f"K={args.k}") if args.k else ("prdp", None, "PRDP")
        sub = out / (f"k{args.k}" if args.k else "prdp")
        runs[label] = runner.run(sc, mode, k, out_dir=sub, resume=_can_resume(args, sub),
                                      k_eps_value=None if baseline is None else baseline.k_eps, **common)
    if baseline is not None:
        runs[f"K_eps={baseline.k_eps}"] = baseline
    if MPI.COMM_WORLD.rank == 0:
        ranks = f" on {MPI.COMM_WORLD.size} ranks ({args.parallel})" if args.parallel else ""
        print(f"scene {sc.name}: {sc.description}{ranks}")
        print(tradeoff.comparison_table(runs))
        print("where the time went [s]:")
        for label, r in runs.items():
            print(f"  {label:<12} " + ", ".join(f"{part.replace('_', ' ')} {sec:.2f}"
                                               for part, sec in tradeoff.time_split(r).items()))
        tradeoff.plot_time_split(runs, out / "time_split.png", sc.name)
        print(f"metrics, checkpoints and time_split.png in {out}")
    return 0


def _methods(args, sc, progress: bool, out: Path) -> int:
    """`fempdl run` and `fempdl compare` on a sip or hig scene: its method and Adam with backpropagation."""
    if args.command == "run":
        if args.save_fields:
            print(f"fempdl: --save-fields writes the fields of PRDP scenes; the {sc.task} scene {sc.name!r} "
                  "reports its errors in metrics.json", file=sys.stderr)
            return 2
        if args.k or args.prdp or args.converged or args.parallel:
            print(f"fempdl: --k, --prdp, --converged and --parallel choose solver caps and ranks for PRDP scenes; "
                  f"the {sc.task} scene {sc.name!r} solves with LU on one process", file=sys.stderr)
            return 2
        names = [sc.task] + ([] if args.no_baseline else [compare.BASELINE])
        runs = {name: runner.run_method(sc, name, out_dir=out / name, progress=progress,
                                        resume=_can_resume(args, out / name), tensorboard=args.tensorboard)
                for name in names}
        print(f"scene {sc.name}: {sc.description}")
        print(compare.table(sc, runs))
        print(f"metrics and checkpoints in {out}")
        return 0
    runs, split, paths = compare.compare_and_report(sc, out, equal_time=not args.equal_iterations_only,
                                                    resume=args.resume, progress=progress)
    print(f"scene {sc.name}: {sc.description}")
    print(compare.table(sc, runs))
    print("\n".join(compare.summary_lines(split)))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _can_resume(args, run_dir: Path) -> bool:
    """--resume continues every run that has a checkpoint (a finished run is not repeated)."""
    return args.resume and (run_dir / CHECKPOINT).exists()


if __name__ == "__main__":
    sys.exit(main())
