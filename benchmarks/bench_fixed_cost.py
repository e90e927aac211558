"""Benchmark: the fixed cost per step of the default scene, at a base revision and at this checkout.

``make run`` trains ``heat-emulator-2d`` with PRDP and with the converged cap
K_eps. This script runs both, at ``--base`` (a git revision, exported with
``git archive`` into a temporary directory) and at this checkout, alternating
the two ``--repeats`` times (``bench_common.interleaved``), each run in a fresh
process, so that both see the same machine load. Recorded per run: the time split of its last metrics row
(:mod:`fempdl.app.runs.timesplit`), its wall time, and ``trainer_seconds``, the
clock around the whole ``Trainer.run`` (which also holds what a revision's
split leaves out, e.g. the files written after the last epoch); per revision
and mode, the medians of the shares of the wall time ("other" and
"validation" above all).

Writes ``bench-results/bench_fixed_cost.json`` (``--out``) through
``bench_common.report``, with the load after every run. Run it as
``python benchmarks/bench_fixed_cost.py --base <revision>``; ``--quick``: one round.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
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
    if not record["fempdl_file"].startswith(str(checkout)):
        raise RuntimeError(f"the run imported {record['fempdl_file']}, not the checkout {checkout}")
    return record


def shares(records: list[dict]) -> dict:
    """Per mode: median wall time, trainer seconds and share of the wall time of each part."""
    from bench_common import reduce
    median = functools.partial(reduce, statistic="median")
    out = {}
    for mode in MODES:
        runs = [r["runs"][mode] for r in records]
        parts = runs[0]["time_split"]
        out[mode] = {"wall_time": median(r["wall_time"] for r in runs),
                     "trainer_seconds": median(r["trainer_seconds"] for r in runs),
                     "outside_the_split_seconds": median(r["trainer_seconds"] - r["wall_time"]
                                                                    for r in runs),
                     "share": {part: median(r["time_split"][part] / r["wall_time"] for r in runs)
                               for part in parts},
                     "seconds": {part: median(r["time_split"][part] for r in runs) for part in parts}}
    return out


def main() -> None:
    import bench_common
    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=3, quick="one round", quick_repeats=1)
    parser.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--base", default="HEAD", help="the git revision to compare against (default HEAD)")
    args = parser.parse_args()
    if args.child is not None:
        child(args.child)
        return
    base_rev = subprocess.run(["git", "-C", str(ROOT), "rev-parse", args.base], check=True, capture_output=True,
                              text=True).stdout.strip()
    with bench_common.report(__file__, args.out, statistic="median", repeats=args.repeats, scene=SCENE,
                             k_eps=K_EPS, base=base_rev, records={"base": [], "this": []}) as record, \
            tempfile.TemporaryDirectory() as tmp:
        base = export(base_rev, Path(tmp) / "base")

        def one_run(label: str, checkout: Path):
            def run() -> None:
                record["records"][label].append(measure(checkout, Path(tmp)))
                record.sample_load(f"after a {label} run")
                print(f"{label}: " + ", ".join(
                    f"{mode} wall {r['wall_time']:.2f} s other {r['time_split']['other'] / r['wall_time']:.1%} "
                    f"validation {r['time_split']['validation'] / r['wall_time']:.1%}"
                    for mode, r in record["records"][label][-1]["runs"].items()), flush=True)
            return run

        bench_common.interleaved({"base": one_run("base", base), "this": one_run("this", ROOT)},
                                 repeats=args.repeats, warmup=0, statistic="median")
        record["median"] = {label: shares(records) for label, records in record["records"].items()}
    print(json.dumps(record["median"], indent=1))


if __name__ == "__main__":
    main()
