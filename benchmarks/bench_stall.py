"""Benchmark: does a training run stall when another busy process shares the cores?

Times ``fempdl run heat-emulator-2d --converged --epochs 10`` as a whole
process alone, and again while a competing process keeps one core busy (a
pure-Python loop), with fempdl's default OpenMP wait policy (PASSIVE) and,
for contrast, with ``OMP_WAIT_POLICY=ACTIVE`` (spinning threads, the OpenMP
runtime's default). The inner-iteration counts of the runs must be equal;
the target is a slowdown of at most 2x with the default policy.

Each case runs ``--repeats`` times; the fastest counts (``bench_common.timed``). Writes
``bench-results/bench_stall.json`` (``--out``) through ``bench_common.report``. Run on an
idle machine; ``--quick``: 2 epochs, one run per case.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import bench_common
from bench_common import timed

FEMPDL = Path(sys.executable).with_name("fempdl")
BUSY = "import time\nend = time.time() + {seconds}\nwhile time.time() < end:\n    pass\n"


def timed_run(scene: str, epochs: int, policy: str | None, competitor: bool) -> dict:
    env = {k: v for k, v in os.environ.items() if k != "OMP_WAIT_POLICY"}
    if policy is not None:
        env["OMP_WAIT_POLICY"] = policy
    busy = subprocess.Popen([sys.executable, "-c", BUSY.format(seconds=600)]) if competitor else None
    try:
        with tempfile.TemporaryDirectory() as out:
            t0 = time.perf_counter()
            subprocess.run([str(FEMPDL), "run", scene, "--converged", "--epochs", str(epochs), "--no-progress",
                            "--out", out], env=env, check=True, capture_output=True)
            seconds = time.perf_counter() - t0
            rows = json.loads((Path(out) / "converged" / "metrics.json").read_text())
    finally:
        if busy is not None:
            busy.kill()
            busy.wait()
    return {"seconds": seconds, "total_iterations": rows[-1]["total_iterations"],
            "final_metric": rows[-1]["val_metric"]}


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=2, quick_repeats=1,
                                 quick="2 epochs")
    parser.add_argument("--scene", default="heat-emulator-2d")
    parser.add_argument("--epochs", type=int, default=None, help="default 10")
    args = parser.parse_args(argv)
    args.epochs = args.epochs or (2 if args.quick else 10)
    with bench_common.report(__file__, args.out, repeats=args.repeats, scene=args.scene, epochs=args.epochs,
                             cases={}) as results:
        run_cases(args, results)
    print(f"inner iterations equal in every case: {results['iterations_equal']}; wrote {args.out}")
    return 0


def run_cases(args, results: dict) -> None:
    for policy in (None, "ACTIVE"):
        label = "default (PASSIVE)" if policy is None else policy
        for competitor in (False, True):
            runs = []

            def one(policy=policy, competitor=competitor, runs=runs) -> float:
                runs.append(timed_run(args.scene, args.epochs, policy, competitor))
                return runs[-1]["seconds"]

            results["cases"][f"{label}, {'with' if competitor else 'without'} a busy process"] = {
                "seconds": timed(one, repeats=args.repeats, warmup=0).seconds, "runs": runs}
        alone, shared = (results["cases"][f"{label}, {w} a busy process"] for w in ("without", "with"))
        results[f"slowdown {label}"] = shared["seconds"] / alone["seconds"]
        print(f"{label}: alone {alone['seconds']:.1f} s, with a busy process {shared['seconds']:.1f} s: "
              f"{results[f'slowdown {label}']:.2f}x", flush=True)
    its = {r["total_iterations"] for case in results["cases"].values() for r in case["runs"]}
    results["iterations_equal"] = len(its) == 1


if __name__ == "__main__":
    sys.exit(main())
