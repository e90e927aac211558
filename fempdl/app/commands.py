"""What the ``fempdl`` command does once its arguments are parsed (:mod:`fempdl.app.cli`): load the
scene, lock the output directory, train the runs, print and write the reports.

The scene is resolved once, into a :class:`~fempdl.app.runs.plan.ScenePlan` (its task looked up, the
caps of the command's runs checked before anything is written, the parallel mode checked), and every
run of the command trains from that plan.

The command records in its output directory what it trains there (command, mode, K, baseline;
:func:`fempdl.app.runs.files.record_command`): a ``--resume`` asking for other runs is refused,
naming what differs, instead of quietly starting them beside the ones it would continue."""
from __future__ import annotations

import contextlib
import dataclasses
import errno
import logging
import sys
from pathlib import Path

from mpi4py import MPI

from fempdl.app import scene
from fempdl.app.reports import compare, tradeoff
from fempdl.app.runs import files, rundir, runner
from fempdl.app.runs.checkpoints import CheckpointError, remove_stale_temporaries
from fempdl.app.runs.plan import ScenePlan
from fempdl.app.runs.settings import RunSettings
from fempdl.core import parallel
from fempdl.solve.stats import SolverFailedError

__all__ = ["execute"]


def execute(args) -> int:
    """Run the command ``args`` (parsed by :func:`fempdl.app.cli.build_parser`); returns the exit code."""
    parallel.abort_on_error()  # under mpirun: one rank's error ends the job, never a hang
    if args.command != "scenes":
        parallel.fit_threads(args.threads)
    try:
        if args.command == "scenes":
            return _scenes(args)
        with _library_log(getattr(args, "log_every", None), MPI.COMM_WORLD.rank):
            return _load_and_run(args)
    except KeyboardInterrupt as interrupted:
        out = getattr(interrupted, "out", None)          # None: interrupted before runs began
        # `fempdl tradeoff` has no --resume: its runs start again whatever they kept.
        kept = out is not None and hasattr(args, "resume") and _checkpoint_kept(out)
        print("fempdl: interrupted; " + ("a run's checkpoint holds its epochs finished up to a second before "
                                         "(continue with --resume)" if kept else
                                         "no checkpoint was written yet, so there is nothing to resume: run the "
                                         "command again"), file=sys.stderr)
        return 130
    except USER_ERRORS as err:
        return _refuse(err)


#: Errors that are about the inputs, the machine or the run's files, not fempdl's code: the command
#: reports them in one line (exit 2) instead of a traceback.
USER_ERRORS = (ValueError, TypeError, OSError, MemoryError, SolverFailedError, rundir.RunDirectoryError,
               CheckpointError)


# A full disk, a full quota, a file beyond the file size limit (ulimit -f; Python ignores SIGXFSZ, so the
# write fails with EFBIG instead of killing the process).
_FULL = (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)


def _refuse(err: BaseException) -> int:
    """Print ``err`` as one line and return the exit code 2; under mpirun end every rank (the others may
    wait in a collective call), without a traceback."""
    message = " ".join(str(err).split()) or type(err).__name__
    if isinstance(err, OSError) and err.errno in _FULL:
        where = repr(str(err.filename)) if err.filename is not None else "the command's files"
        message = (f"cannot write {where} ({err.strerror}); "
                   f"{files.size_limit_advice(err) or 'free some space on its file system or choose another --out'}")
    elif isinstance(err, OSError) and not isinstance(err, FileNotFoundError) and err.strerror:
        message = f"{err.strerror}: {err.filename or message}" if err.filename else message
    comm = MPI.COMM_WORLD
    print(f"fempdl: {f'[rank {comm.rank}] ' if comm.size > 1 else ''}{message}", file=sys.stderr, flush=True)
    if comm.size > 1:
        comm.Abort(2)
    return 2


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
    names = scene.available()
    width = max(map(len, names), default=0)
    for name in names:
        print(f"{name:<{width}} {scene.load(name).description}")
    return 0


def _load_and_run(args) -> int:
    comm = MPI.COMM_WORLD
    try:
        sc = scene.load(args.scene, args.set)
        error = None
    except scene.SceneError as err:
        error = err
    # Every rank loads the scene first: a name or key wrong on all of them is said once, by rank 0;
    # a file one rank alone cannot read is that rank's error (and ends the job).
    if comm.size > 1 and comm.allreduce(error is not None, op=MPI.LAND):
        if comm.rank == 0:
            print(f"fempdl: {' '.join(str(error).split())}", file=sys.stderr, flush=True)
        return 2
    if error is not None:
        raise error
    if args.epochs is not None:
        sc = dataclasses.replace(sc, optimizer=dataclasses.replace(sc.optimizer, epochs=args.epochs))
    plan = ScenePlan.of(sc)             # the scene's task looked up once, for the whole command
    refusal = _ranks_refusal(args, plan, MPI.COMM_WORLD.size)
    if refusal is not None:
        if MPI.COMM_WORLD.rank == 0:
            print(f"fempdl: {refusal}", file=sys.stderr)
        return 2
    plan = _plan_caps(args, plan)
    out = _output_directory(args, plan)
    # The whole command holds the lock: a second command on the same --out is refused,
    # not only a second run in one of its subdirectories.
    with rundir.RunLock(out) if MPI.COMM_WORLD.rank == 0 else contextlib.nullcontext():
        if MPI.COMM_WORLD.rank == 0:
            remove_stale_temporaries(out)       # of reports a killed command was writing
            files.record_command(out, _command_record(args, plan))
        try:
            return _command(args, plan, out)
        except KeyboardInterrupt as err:
            raise _Interrupted(out) from err


class _Interrupted(KeyboardInterrupt):
    """Ctrl-C while a command's runs trained into ``out``."""

    def __init__(self, out: Path):
        super().__init__()
        self.out = out


def _checkpoint_kept(out: Path) -> bool:
    """Whether a run under ``out`` (``out`` itself or a folder in it) has a checkpoint to continue from."""
    return rundir.can_resume(out) or any(rundir.can_resume(d) for d in Path(out).iterdir()
                                         if d.is_dir() and not d.is_symlink())


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


def _ranks_refusal(args, plan: ScenePlan, ranks: int) -> str | None:
    """Why the command cannot run the plan's scene on ``ranks`` processes as asked (None if it can):
    without a ``--parallel`` mode every rank would train the same runs and write the same files."""
    if ranks == 1 or getattr(args, "parallel", None) is not None:
        return None
    modes = plan.spec.parallel
    if not modes:           # sip and hig scenes: the plan says why they train on one process
        return plan.parallel_refusal("data")
    one_run = f"`fempdl run {plan.name} --parallel {'|'.join(modes)}`"
    if args.command == "run":
        return f"running on {ranks} ranks needs a mode: {one_run}"
    return (f"`fempdl {args.command}` trains its runs on one process; run it without mpirun (one run on "
            f"{ranks} ranks: {one_run})")


def _plan_caps(args, plan: ScenePlan) -> ScenePlan:
    """The plan with the caps of the command's runs checked (the converged baseline; --k or --ks, and
    PRDP's [prdp] k0 and k_cap), so that a cap no solve could take is refused before anything is
    written or trained: it used to be refused only when its own run began, after the baseline had
    trained. The runs take their caps from the plan; nothing checks them again."""
    if plan.trains_methods or args.command not in ("run", "tradeoff"):
        return plan     # `fempdl compare` on a solver-cap scene is refused as it is
    baseline = [("converged", None)] if args.command == "tradeoff" or args.converged or not args.no_baseline else []
    fixed = [("fixed", args.k, "--k")] if args.command == "run" and args.k else [("fixed", k, "--ks") for k in
                                                                                getattr(args, "ks", None) or ()]
    prdp = [("prdp", None)] if args.command == "tradeoff" or not (args.k or args.converged) else []
    return plan.with_caps(*fixed, *prdp, *baseline)


def _output_directory(args, plan: ScenePlan) -> Path:
    """--out, or runs/<scene name>[/tradeoff|/compare]; refused (RunDirectoryError) when it holds a run
    that neither --resume nor --overwrite says what to do with, or files of the user's without --overwrite
    (:func:`fempdl.app.runs.rundir.check_output_directory`)."""
    default = rundir.child(Path("runs"), plan.name, "scene name")
    out = args.out or {"run": default, "tradeoff": default / "tradeoff", "compare": default / "compare"}[args.command]
    resume = getattr(args, "resume", False)
    if resume and args.overwrite:
        raise rundir.RunDirectoryError("--resume and --overwrite contradict each other: give one")
    rundir.check_output_directory(out, resume=resume, overwrite=args.overwrite)
    refusal = None
    if resume and rundir.holds_run(out):
        refusal = _resume_refusal(out, _recorded_command(out), _command_record(args, plan))
    if refusal is not None:
        raise rundir.RunDirectoryError(refusal)
    return out


def _command_record(args, plan: ScenePlan) -> dict:
    """What the command trains into its output directory, which a --resume must ask for again."""
    if args.command != "run":
        return {"command": args.command}
    baseline = args.converged or not args.no_baseline
    if plan.trains_methods:
        return {"command": "run", "baseline": baseline}
    mode = "converged" if args.converged else "fixed" if args.k else "prdp"
    return {"command": "run", "mode": mode, "k": args.k, "baseline": baseline}


def _recorded_command(out: Path) -> dict | None:
    """What the record of ``out`` says the command trained there, or None when it says nothing that
    :func:`_command_record` gives (the record was edited or damaged, or the runs were trained through
    the Python API, which records no command)."""
    record = files.command_of(out)
    if record is None or record.get("command") not in ("run", "tradeoff", "compare"):
        return None
    if record["command"] != "run":
        return record
    mode, k = record.get("mode"), record.get("k")
    cap = (mode == "fixed" and type(k) is int and k >= 1) or (mode in ("prdp", "converged", None) and k is None)
    return record if isinstance(record.get("baseline"), bool) and cap else None


def _resume_refusal(out: Path, earlier: dict | None, now: dict) -> str | None:
    """Why --resume refuses (None: it does not): the runs in ``out`` were started by another command or
    with another mode, K or baseline, so resuming would start new runs beside them; or its record does
    not say how they were started (``earlier`` None), so resuming could do the same."""
    if earlier is None:
        # Treated as the record of another command: nothing can be continued as it was started.
        changes = [f"its record {str(Path(out) / files.RECORD)!r} does not say which command started them "
                   "(it was edited or damaged, or they were trained through the Python API)"]
    elif earlier.get("command") != now["command"]:
        changes = [f"they are of `fempdl {earlier.get('command')}`, not `fempdl {now['command']}`"]
    else:
        changes = []
        if earlier.get("mode") != now.get("mode"):
            changes.append(f"mode was {_mode_text(earlier)}, now {_mode_text(now)}")
        elif earlier.get("k") != now.get("k"):
            changes.append(f"k was {earlier.get('k')}, now {now.get('k')}")
        if earlier.get("baseline") != now.get("baseline"):
            trained = {True: "trained", False: "skipped (--no-baseline)"}
            changes.append(f"the baseline was {trained[earlier['baseline']]}, now {trained[now['baseline']]}")
    if not changes:
        return None
    # `fempdl tradeoff` has no --resume: its runs, like those of a record that names no command, are
    # not continued by any command line.
    again = ("" if earlier is None or earlier["command"] == "tradeoff" else
             f"continue them with `{_command_line(earlier)}`, or ")
    return (f"--resume continues the runs in {str(out)!r} as they were started, and {'; '.join(changes)}: "
            f"{again}start the new runs in another --out (or replace those with --overwrite instead of --resume)")


def _mode_text(record: dict) -> str:
    return f"fixed K={record.get('k')}" if record.get("mode") == "fixed" else str(record.get("mode"))


def _command_line(record: dict) -> str:
    """The options of ``fempdl run`` (or the command) that started the runs of ``record``, with --resume."""
    flags = {"fixed": f"--k {record.get('k')}", "prdp": "--prdp", "converged": "--converged"}.get(record.get("mode"))
    parts = [f"fempdl {record.get('command')}", *([flags] if flags else []),
             *(["--no-baseline"] if record.get("baseline") is False and record.get("mode") != "converged" else [])]
    return " ".join(parts + ["--resume"])


def _command(args, plan: ScenePlan, out: Path) -> int:
    """The run, tradeoff or compare command of a planned scene, into ``out``."""
    progress = not args.no_progress and sys.stderr.isatty()
    sc = plan.scene
    if (args.command == "compare") != plan.trains_methods and args.command != "run":
        use = "fempdl compare" if plan.trains_methods else "fempdl tradeoff"
        print(f"fempdl: `fempdl {args.command}` does not apply to the {sc.task} scene {sc.name!r}; use `{use}`",
              file=sys.stderr)
        return 2
    if plan.trains_methods:
        return _methods(args, plan, progress, out)
    if args.command == "tradeoff":
        runs = tradeoff.sweep(plan, ks=args.ks, out_dir=out, progress=progress, overwrite=args.overwrite)
        split = tradeoff.savings(runs, stop_at=sc.optimizer.stop_at, refine=sc.solver.refine)
        paths = tradeoff.write_report(sc, runs, split, out)
        print(tradeoff.comparison_table(runs))
        print("\n".join(tradeoff.summary_lines(split)))
        print("wrote " + ", ".join(str(p) for p in paths))
        return 0

    try:
        plan = plan.in_parallel(args.parallel)
    except ValueError as err:
        print(f"fempdl: {err}", file=sys.stderr)
        return 2
    if args.save_fields and not plan.spec.writes_fields:
        print(f"fempdl: --save-fields writes the fields of {' and '.join(runner.field_tasks())} scenes; "
              f"{sc.name!r} is of task {sc.task!r}", file=sys.stderr)
        return 2
    runs = {}
    baseline = None
    common = RunSettings(progress=progress, parallel=args.parallel, seed=args.seed, save=args.save_fields,
                         tensorboard=args.tensorboard)
    if not args.no_baseline or args.converged:
        baseline = runner.train(plan, plan.caps("converged"), common, out_dir=out / "converged",
                                **_run_files(args, out / "converged"))
        plan = plan.measured(baseline.k_eps, baseline.converged_caps)      # the next run takes them
    if not args.converged:
        mode, k, label = ("fixed", args.k, f"K={args.k}") if args.k else ("prdp", None, "PRDP")
        sub = out / (f"k{args.k}" if args.k else "prdp")
        runs[label] = runner.train(plan, plan.caps(mode, k), common, out_dir=sub, **_run_files(args, sub))
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


def _methods(args, plan: ScenePlan, progress: bool, out: Path) -> int:
    """`fempdl run` and `fempdl compare` on a sip or hig scene: its method and Adam with backpropagation."""
    sc = plan.scene
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
        common = RunSettings(progress=progress, tensorboard=args.tensorboard)
        runs = {name: runner.train_method(plan, name, common, out_dir=out / name, **_run_files(args, out / name))
                for name in names}
        print(f"scene {sc.name}: {sc.description}")
        print(compare.table(sc, runs))
        print(f"metrics and checkpoints in {out}")
        return 0
    runs, split, paths = compare.compare_and_report(plan, out, equal_time=not args.equal_iterations_only,
                                                    resume=args.resume, progress=progress,
                                                    overwrite=args.overwrite)
    print(f"scene {sc.name}: {sc.description}")
    print(compare.table(sc, runs))
    print("\n".join(compare.summary_lines(split)))
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def _run_files(args, run_dir: Path) -> dict:
    """``resume`` and ``overwrite`` for one run of the command. --resume continues every run that has
    a checkpoint fempdl wrote (a finished run is not repeated) and starts the others afresh (runs the
    command had not begun, or that ended before their first checkpoint), replacing only files fempdl
    wrote there: it never turns overwrite on for a directory holding files of yours. --overwrite
    replaces them."""
    resume = getattr(args, "resume", False)
    again = resume and rundir.can_resume(run_dir)
    return {"resume": again,
            "overwrite": not again and (args.overwrite or (resume and not rundir.foreign_entries(run_dir)))}

