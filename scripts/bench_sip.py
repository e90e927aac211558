"""Benchmark: SIP and HIG against Adam with backpropagation, on the bundled sip and hig scenes.

For every scene, :func:`fempdl.app.reports.compare.compare` trains the scene's method and
then the baseline (Adam, gradients backpropagated through the LU solve) from
the same initial network, for the scene's epochs; the baseline then goes on
until it has used the method's training time (at most 20x the iterations).
Recorded per scene: the validation metric of both (x error for sip scenes,
observation nMSE for hig-poisson) after equal iterations and at equal
training time, their ratios method / baseline, and the seconds per
iteration. OpenMP threads wait passively (``OMP_WAIT_POLICY=PASSIVE`` unless
the environment sets it; the policy is recorded): the default policy made HIG
steps 2-10x slower, at random, whenever another process held a core. Torch runs
on one thread (``--threads``): at these sizes (a 264 x 2.1k Jacobian) a HIG
step took 20-26 ms on one thread and 40-42 ms on two, and two threads slowed
further, to 100-170 ms, in periods when this shared machine was busy. Each
scene's report (JSON, CSV, the plot against iterations and
time) goes to ``bench-results/sip/<scene>/``; the summary to
``bench-results/bench_sip.json`` (``--out``).
Run: ``python scripts/bench_sip.py`` (a few minutes on 2 cores).
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")    # before torch starts its threads (bench_unrolled.py)

import torch  # noqa: E402

from fempdl.app.reports import compare
from fempdl.app import scene  # noqa: E402
from fempdl.app.cli import positive_int  # noqa: E402

from bench_common import comma_list, machine_info, write_json_atomically  # noqa: E402

SCENES = ["sip-poisson", "sip-heat", "hig-poisson"]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scenes", type=comma_list(str), default=SCENES)
    parser.add_argument("--epochs", type=positive_int, help="override every scene's epochs")
    parser.add_argument("--out", type=Path, default=Path("bench-results/bench_sip.json"))
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads for both methods (default 1: faster at these sizes, see above)")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    results = {"machine": machine_info(), "settings": {k: str(v) for k, v in vars(args).items()}}
    for name in args.scenes:
        sc = scene.load(name)
        if args.epochs:
            sc = dataclasses.replace(sc, optimizer=dataclasses.replace(sc.optimizer, epochs=args.epochs))
        report_dir = args.out.parent / "sip" / name
        runs, split, _ = compare.compare_and_report(sc, report_dir)
        results[name] = {"scene": sc.as_dict(), **split}
        print(f"{name}:\n" + compare.table(sc, runs) + "\n" + "\n".join(compare.summary_lines(split)), flush=True)
        write_json_atomically(results, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
