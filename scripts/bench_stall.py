"""Benchmark: does a training run stall when another busy process shares the cores?

Times ``fempdl run heat-emulator-2d --converged --epochs 10`` as a whole
process alone, and again while a competing process keeps one core busy (a
pure-Python loop), with fempdl's default OpenMP wait policy (PASSIVE) and,
for contrast, with ``OMP_WAIT_POLICY=ACTIVE`` (spinning threads, the OpenMP
runtime's default). The inner-iteration counts of the runs must be equal;
the target is a slowdown of at most 2x with the default policy.

Writes ``bench-results/bench_stall.json`` (``--out``). Run on an idle machine.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench_common import machine_info, write_json_atomically

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
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", default="heat-emulator-2d")
    parser.add_argument("--epochs", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=2, help="runs per case (the minimum time is kept)")
    parser.add_argument("--out", type=Path, default=Path("bench-results/bench_stall.json"))
    args = parser.parse_args(argv)
    results = {"machine": machine_info(), "scene": args.scene, "epochs": args.epochs, "cases": {}}
    for policy in (None, "ACTIVE"):
        label = "default (PASSIVE)" if policy is None else policy
        for competitor in (False, True):
            runs = [timed_run(args.scene, args.epochs, policy, competitor) for _ in range(args.repeats)]
            results["cases"][f"{label}, {'with' if competitor else 'without'} a busy process"] = {
                "seconds": min(r["seconds"] for r in runs), "runs": runs}
        alone, shared = (results["cases"][f"{label}, {w} a busy process"] for w in ("without", "with"))
        results[f"slowdown {label}"] = shared["seconds"] / alone["seconds"]
        print(f"{label}: alone {alone['seconds']:.1f} s, with a busy process {shared['seconds']:.1f} s: "
              f"{results[f'slowdown {label}']:.2f}x", flush=True)
    its = {r["total_iterations"] for case in results["cases"].values() for r in case["runs"]}
    results["iterations_equal"] = len(its) == 1
    results["machine"]["load_average_1_5_15_min_at_end"] = list(os.getloadavg())
    write_json_atomically(results, args.out)
    print(f"inner iterations equal in every case: {results['iterations_equal']}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
