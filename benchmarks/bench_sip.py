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
``bench-results/bench_sip.json`` (``--out``, through ``bench_common.report``); ``--quick``:
sip-poisson, 5 epochs.
Run: ``python benchmarks/bench_sip.py`` (a few minutes on 2 cores). With
``--seeds 0,1,2`` every scene is compared once per seed (``[data] seed``: the
truths and the network's initialisation), the reports going to
``bench-results/sip/<scene>/seed<k>/``, and the JSON holds each seed's summary
and the seeds' mean ratios; the nonlinear scenes are recorded that way:
``python benchmarks/bench_sip.py --scenes sip-nonlinear,hig-nonlinear --seeds 0,1,2
--out bench-results/bench_sip_nonlinear.json``.
"""
from __future__ import annotations

import dataclasses
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")    # before torch starts its threads (bench_unrolled.py)

import torch  # noqa: E402

from fempdl.app import scene  # noqa: E402
from fempdl.app.cli import positive_int  # noqa: E402
from fempdl.app.reports import compare

import bench_common  # noqa: E402
from bench_common import comma_list  # noqa: E402

SCENES = ["sip-poisson", "sip-heat", "hig-poisson"]


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=None,
                                 quick="sip-poisson only, 5 epochs (explicit flags still win)")
    parser.add_argument("--scenes", type=comma_list(str), default=None, help=f"default {','.join(SCENES)}")
    parser.add_argument("--epochs", type=positive_int, help="override every scene's epochs")
    parser.add_argument("--threads", type=int, default=1,
                        help="torch threads for both methods (default 1: faster at these sizes, see above)")
    parser.add_argument("--seeds", type=comma_list(int),
                        help="compare once per [data] seed (truths and network initialisation); default: the scene's")
    args = parser.parse_args(argv)
    args.scenes = args.scenes or (["sip-poisson"] if args.quick else SCENES)
    args.epochs = args.epochs or (5 if args.quick else None)
    torch.set_num_threads(args.threads)
    # single runs (means over the seeds with --seeds)
    with bench_common.report(__file__, args.out, statistic="mean", repeats=1,
                             settings={k: str(v) for k, v in vars(args).items()}) as results:
        run_scenes(args, results)
    return 0


def run_scenes(args, results: bench_common.Report) -> None:
    for name in args.scenes:
        sc = scene.load(name)
        if args.epochs:
            sc = dataclasses.replace(sc, optimizer=dataclasses.replace(sc.optimizer, epochs=args.epochs))
        if args.seeds is None:
            results[name] = {"scene": sc.as_dict(), **compare_one(sc, args.out.parent / "sip" / name)}
        else:
            results[name] = seeded(sc, args.seeds, args.out.parent / "sip" / name)
        results.save()


def compare_one(sc, report_dir: Path) -> dict:
    runs, split, _ = compare.compare_and_report(sc, report_dir, overwrite=True)
    print(f"{sc.name} (seed {sc.data.seed}):\n" + compare.table(sc, runs) + "\n"
          + "\n".join(compare.summary_lines(split)), flush=True)
    return split


def seeded(sc, seeds: list, report_dir: Path) -> dict:
    """One comparison per seed, and the seeds' means of the ratios (equal-time ones where every seed has one)."""
    per_seed = {}
    for seed in seeds:
        run_scene = dataclasses.replace(sc, data=dataclasses.replace(sc.data, seed=seed))
        per_seed[seed] = compare_one(run_scene, report_dir / f"seed{seed}")
    splits = list(per_seed.values())
    out = {"scene": sc.as_dict(), "seeds": seeds, "per_seed": {str(k): v for k, v in per_seed.items()}}
    for key in ("ratio_equal_iterations", "ratio_equal_time", "method_metric", "baseline_metric",
                "baseline_metric_at_equal_time", "baseline_iterations_in_that_time", "equal_time_seconds"):
        values = [s[key] for s in splits]
        if all(v is not None for v in values):
            out[f"mean_{key}"] = statistics.mean(values)
            out[f"range_{key}"] = [min(values), max(values)]
    out["seconds_per_iteration"] = {name: statistics.mean(s["seconds_per_iteration"][name] for s in splits)
                                    for name in splits[0]["seconds_per_iteration"]}
    print(f"{sc.name} over seeds {seeds}: method / Adam at equal iterations {out['mean_ratio_equal_iterations']:.3f} "
          f"({out['range_ratio_equal_iterations'][0]:.3f}-{out['range_ratio_equal_iterations'][1]:.3f})"
          + (f", at equal time {out['mean_ratio_equal_time']:.3f}" if "mean_ratio_equal_time" in out else ""),
          flush=True)
    return out


if __name__ == "__main__":
    sys.exit(main())
