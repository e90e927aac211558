"""Making a ("revolve", s) schedule: fempdl's lazy BinomialRevolve against checkpoint_schedules' Revolve.

For each N the whole action stream is built and iterated to its EndReverse, as a Rollout's forward
and backward consume it, without running any step: what the schedule alone costs. Each measurement
runs in a fresh process (``--worker``), which reports the time to build the schedule, the time to
iterate its actions, the number of actions, the steps of the first sweep and those run again, and
its peak resident memory. checkpoint_schedules' Revolve builds its whole schedule up front; it is
given ``--timeout`` seconds per N and recorded as unfinished beyond that. The steps run again must
agree between the two where both finish, and equal ``recomputed_steps(N, s)``. A last row times the
first sweep of an N = 10^9 stream (its actions up to EndForward and the first Reverse).

Each fempdl N runs ``--repeats`` times; the fastest counts (``bench_common.repeat_runs``). Writes
``bench-results/bench_revolve.json`` (``--out``) through ``bench_common.report``.
Run (from the repository root, on an idle machine)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_revolve.py
    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_revolve.py --quick     # a smoke test, seconds
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import bench_common

REVOLVE = Path(__file__).resolve().parent.parent / "fempdl" / "layer" / "revolve.py"


def measure(kind: str, steps: int, snapshots: int, first_sweep_only: bool) -> dict:
    """One schedule built and iterated in this process (the worker's side)."""
    import importlib.util

    import checkpoint_schedules as cs

    # The module file alone (it needs only checkpoint_schedules): importing the fempdl package would load
    # the FE stack, hundreds of MiB that would hide the schedule's own memory in the peak.
    spec = importlib.util.spec_from_file_location("revolve", REVOLVE)
    revolve = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(revolve)
    make = {"fempdl": revolve.BinomialRevolve, "checkpoint_schedules": cs.Revolve}[kind]
    rss_before = _peak_rss_mib()
    t0 = time.perf_counter()
    schedule = make(steps, snapshots)
    t1 = time.perf_counter()
    actions = first = again = 0
    swept = False
    for action in schedule:
        actions += 1
        if isinstance(action, cs.Forward):
            if swept:
                again += action.n1 - action.n0
            else:
                first += action.n1 - action.n0
        elif isinstance(action, cs.EndForward):
            swept = True
        elif isinstance(action, cs.Reverse) and first_sweep_only:
            break
        elif isinstance(action, cs.EndReverse):
            break
    t2 = time.perf_counter()
    row = {"schedule": kind, "steps": steps, "snapshots": snapshots, "finished": True,
           "build_s": t1 - t0, "iterate_s": t2 - t1, "total_s": t2 - t0, "actions": actions,
           "first_sweep_steps": first, "peak_rss_mib": _peak_rss_mib(),
           "rss_before_build_mib": rss_before}
    if first_sweep_only:
        row["measured"] = "build and the actions up to the first Reverse"
    else:
        row.update(recomputed=again, recomputed_closed_form=revolve.recomputed_steps(steps, snapshots))
    return row


def _peak_rss_mib() -> float:
    """This process's peak resident memory: VmHWM, which starts again at exec (getrusage's ru_maxrss keeps
    the high-water mark of the driver that forked the worker)."""
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def run_worker(kind: str, steps: int, snapshots: int, timeout: float, first_sweep_only: bool = False) -> dict:
    command = [sys.executable, __file__, "--worker", kind, str(steps), str(snapshots)]
    if first_sweep_only:
        command.append("--first-sweep-only")
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=timeout, env=env)
    except subprocess.TimeoutExpired:
        return {"schedule": kind, "steps": steps, "snapshots": snapshots, "finished": False,
                "note": f"not finished within {timeout:g} s (build and iterate)"}
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=3, quick_repeats=1,
                                 quick="small N and s = 20, a 60 s timeout")
    parser.add_argument("--snapshots", type=int, default=100)
    parser.add_argument("--steps", type=lambda t: [int(x) for x in t.split(",") if x], default=None,
                        help="N for fempdl's schedule (default 1000,10000,100000)")
    parser.add_argument("--cs-steps", type=lambda t: [int(x) for x in t.split(",") if x], default=None,
                        help="N for checkpoint_schedules' Revolve (default 1000,2000)")
    parser.add_argument("--timeout", type=float, default=90.0, help="seconds per checkpoint_schedules run")
    parser.add_argument("--worker", nargs=3, metavar=("KIND", "N", "S"), help=argparse.SUPPRESS)
    parser.add_argument("--first-sweep-only", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        kind, steps, snapshots = args.worker
        print(json.dumps(measure(kind, int(steps), int(snapshots), args.first_sweep_only)))
        return 0

    if args.quick:
        args.steps = args.steps or [1000, 2000]
        args.cs_steps = args.cs_steps or [200]
        args.snapshots = min(args.snapshots, 20)
        args.timeout = min(args.timeout, 60.0)
    args.steps = args.steps or [1000, 10_000, 100_000]
    args.cs_steps = args.cs_steps or [1000, 2000]
    # The machine record imports the FE stack: only the driver pays for it, not the workers it measures.
    with bench_common.report(__file__, args.out, repeats=args.repeats, snapshots=args.snapshots,
                             timeout_s=args.timeout, quick=args.quick, rows=[]) as data:
        measure_all(args, data)
    print(f"wrote {args.out}; steps run again agree: {data['recomputed_agree']}")
    return 0 if data["recomputed_agree"] else 1


def measure_all(args, data: dict) -> None:
    for steps in args.steps:
        data["rows"].append(bench_common.repeat_runs(
            functools.partial(run_worker, "fempdl", steps, args.snapshots, timeout=3600), "total_s",
            repeats=args.repeats))
        print(json.dumps(data["rows"][-1]), flush=True)
    for steps in args.cs_steps:
        data["rows"].append(run_worker("checkpoint_schedules", steps, args.snapshots, timeout=args.timeout))
        print(json.dumps(data["rows"][-1]), flush=True)
    data["rows"].append(run_worker("fempdl", 10**9, args.snapshots, timeout=600, first_sweep_only=True))
    print(json.dumps(data["rows"][-1]), flush=True)
    agree = {}
    for row in data["rows"]:
        if row["finished"] and "recomputed" in row:
            agree.setdefault(row["steps"], set()).update({row["recomputed"], row["recomputed_closed_form"]})
    data["recomputed_agree"] = all(len(values) == 1 for values in agree.values())


if __name__ == "__main__":
    sys.exit(main())
