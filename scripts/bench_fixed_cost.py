"""Benchmark: the fixed cost per step of the default scene, at a base revision and at this checkout.

``make run`` trains ``heat-emulator-2d`` with PRDP and with the converged cap
K_eps. This script runs both, at ``--base`` (a git revision, exported with
``git archive`` into a temporary directory) and at this checkout, alternating
the two ``--rounds`` times, each run in a fresh process, so that both see the
same machine load. Recorded per run: the time split of its last metrics row
(:mod:`fempdl.app.runs.timesplit`), its wall time, and ``trainer_seconds``, the
clock around the whole ``Trainer.run`` (which also holds what a revision's
split leaves out, e.g. the files written after the last epoch); per revision
and mode, the medians of the shares of the wall time ("other" and
"validation" above all).

Writes ``bench-results/bench_fixed_cost.json`` (``--out``). Run it as
``python scripts/bench_fixed_cost.py --base <revision>``; it records the load.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
SCENE, K_EPS = "heat-emulator-2d", 27       # the scene's K_eps (measured by `fempdl run`; fixed here to save time)
MODES = ("prdp", "converged")


def child(out: Path) -> None:
    """One run of each mode in this process (fempdl from PYTHONPATH); a JSON record to ``out``."""
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
    from mpi4py import MPI  # noqa: F401  (before DOLFINx)

    import fempdl
    from fempdl.app import scene
    from fempdl.app.runs import runner, training

    seconds = []
    timed = training.Trainer.run

    def run(self, *args, **kwargs):
        t0 = time.perf_counter()
        try:
            return timed(self, *args, **kwargs)
        finally:
            seconds.append(time.perf_counter() - t0)

    training.Trainer.run = run
    record = {"fempdl_file": fempdl.__file__, "runs": {}}
    sc = scene.load(SCENE)
    with tempfile.TemporaryDirectory() as tmp:
        for mode in MODES:
            result = runner.run(sc, mode, out_dir=Path(tmp) / mode, k_eps_value=K_EPS, overwrite=True)
            last = result.rows[-1]
            split = {key[len("time_"):]: value for key, value in last.items() if key.startswith("time_")}
            record["runs"][mode] = {"wall_time": last["wall_time"], "trainer_seconds": seconds[-1],
                                    "time_split": split, "final_metric": last["val_metric"],
                                    "total_iterations": last["total_iterations"], "epochs": len(result.rows)}
    out.write_text(json.dumps(record))


def export(revision: str, into: Path) -> Path:
    """The files of ``revision`` of this repository, extracted into ``into``."""
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", revision],
                             check=True, capture_output=True).stdout
    with tarfile.open(fileobj=__import__("io").BytesIO(archive)) as tar:
        tar.extractall(into)
    return into


def measure(checkout: Path, scratch: Path) -> dict:
    out = scratch / "child.json"
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_WAIT_POLICY": "PASSIVE"}
    subprocess.run([sys.executable, str(HERE / "bench_fixed_cost.py"), "--child", str(out)], env=env, check=True,
                   cwd=scratch)
    record = json.loads(out.read_text())
    record["load_average_1_min_after"] = os.getloadavg()[0]
    if not record["fempdl_file"].startswith(str(checkout)):
        raise RuntimeError(f"the run imported {record['fempdl_file']}, not the checkout {checkout}")
    return record


def shares(records: list[dict]) -> dict:
    """Per mode: median wall time, trainer seconds and share of the wall time of each part."""
    out = {}
    for mode in MODES:
        runs = [r["runs"][mode] for r in records]
        parts = runs[0]["time_split"]
        out[mode] = {"wall_time": statistics.median(r["wall_time"] for r in runs),
                     "trainer_seconds": statistics.median(r["trainer_seconds"] for r in runs),
                     "outside_the_split_seconds": statistics.median(r["trainer_seconds"] - r["wall_time"]
                                                                    for r in runs),
                     "share": {part: statistics.median(r["time_split"][part] / r["wall_time"] for r in runs)
                               for part in parts},
                     "seconds": {part: statistics.median(r["time_split"][part] for r in runs) for part in parts}}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--base", default="HEAD", help="the git revision to compare against (default HEAD)")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--out", type=Path, default=ROOT / "bench-results" / "bench_fixed_cost.json")
    args = parser.parse_args()
    if args.child is not None:
        child(args.child)
        return
    from bench_common import machine_info, write_json_atomically
    base_rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", args.base], check=True, capture_output=True,
                              text=True).stdout.strip()
    record = {"benchmark": "bench_fixed_cost", "scene": SCENE, "k_eps": K_EPS, "machine": machine_info(),
              "base": base_rev, "rounds": args.rounds, "records": {"base": [], "this": []}}
    with tempfile.TemporaryDirectory() as tmp:
        base = export(base_rev, Path(tmp) / "base")
        for i in range(args.rounds):
            for label, checkout in (("base", base), ("this", ROOT)):
                record["records"][label].append(measure(checkout, Path(tmp)))
                print(f"round {i + 1} {label}: " + ", ".join(
                    f"{mode} wall {r['wall_time']:.2f} s other {r['time_split']['other'] / r['wall_time']:.1%} "
                    f"validation {r['time_split']['validation'] / r['wall_time']:.1%}"
                    for mode, r in record["records"][label][-1]["runs"].items()), flush=True)
    record["median"] = {label: shares(records) for label, records in record["records"].items()}
    record["load_average_1_5_15_min_at_end"] = list(os.getloadavg())
    write_json_atomically(record, args.out)
    print(json.dumps(record["median"], indent=1))


if __name__ == "__main__":
    main()
