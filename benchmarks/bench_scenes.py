"""Benchmark: PRDP against converged physics on the bundled PRDP scenes, over seeds.

For each scene and each seed (network initialisation and minibatch order;
the data are the scene's): one training run with the converged cap K_eps (the
baseline) and one with PRDP, one after the other in this process, so both see
the same machine load. Recorded per run: the final validation metric,
cumulative forward + backward inner iterations, wall time and where it went
(solver iterations, set-up, assembly, adjoint operator, network, validation,
other), and the K schedule. Per scene: PRDP / baseline ratios of the seeds'
means (metric, iterations, wall time) and each seed's ratios (the spread);
with ``--sweep`` also the fixed-K sweep of :mod:`fempdl.app.reports.tradeoff` (seed 0)
and PRDP's saving split into incomplete-convergence and progressive-refinement
parts. The summary averages the savings over the scenes. On a Newton scene
(a nonlinear PDE) each run also records its Newton steps (forward and
unrolled backward; its iterations are the inner Krylov ones) and their ratio.

Writes ``bench-results/bench_scenes.json`` (``--out``, through ``bench_common.report``:
single runs, statistic "mean" over the seeds) after every scene; ``--quick``:
heat-emulator-2d, seed 0.
Run on an idle machine: ``python benchmarks/bench_scenes.py --threads 1``. The
nonlinear emulator is kept apart from the six PRDP scenes the README averages:
``python benchmarks/bench_scenes.py --threads 1 --scenes nonlinear-heat-emulator
--sweep nonlinear-heat-emulator --out bench-results/bench_nonlinear_scenes.json``.
"""
from __future__ import annotations

import json
import statistics
import sys

import torch

from fempdl.app import scene
from fempdl.app.reports import tradeoff
from fempdl.app.runs import runner

import bench_common
from bench_common import comma_list

PRDP_SCENES = ["heat-emulator-2d", "heat-emulator-3d", "poisson-inverse", "poisson-inverse-3",
               "burgers-emulator", "ns-hybrid"]


def summary(run) -> dict:
    out = {"final_metric": run.final_metric, "total_iterations": run.total_iterations,
           "wall_time": run.wall_time, "train_time": run.rows[-1]["train_time"],
           "time_split": tradeoff.time_split(run), "k_schedule": run.k_schedule, "epochs": len(run.rows)}
    if run.newton_steps is not None:
        out["newton_steps"] = run.newton_steps
    return out


def _ratio(prdp: list, base: list, key: str) -> float:
    return statistics.mean(r[key] for r in prdp) / statistics.mean(r[key] for r in base)


def bench_scene(name: str, seeds: list[int], sweep: bool) -> dict:
    sc = scene.load(name)
    base, prdp, k_eps = [], [], None
    for seed in seeds:
        b = runner.run(sc, "converged", seed=seed, k_eps_value=k_eps)
        k_eps = b.k_eps
        p = runner.run(sc, "prdp", seed=seed, k_eps_value=k_eps)
        base.append(summary(b))
        prdp.append(summary(p))
    keys = ("final_metric", "total_iterations", "wall_time") + (("newton_steps",) if "newton_steps" in base[0] else ())
    out = {"k_eps": k_eps, "seeds": seeds, "converged": base, "prdp": prdp,
           "ratios": {key: _ratio(prdp, base, key) for key in keys + ("train_time",)},
           "ratios_per_seed": [{key: p[key] / b[key] for key in keys} for p, b in zip(prdp, base)]}
    out["iteration_savings"] = 1.0 - out["ratios"]["total_iterations"]
    out["wall_time_savings"] = 1.0 - out["ratios"]["wall_time"]
    if sweep:
        runs = tradeoff.sweep(sc)
        out["sweep"] = {"savings": tradeoff.savings(runs, stop_at=sc.optimizer.stop_at, refine=sc.solver.refine),
                        "runs": {label: summary(r) for label, r in runs.items()}}
    return out


def markdown_table(results: dict) -> str:
    """The table of docs/scenes.md: per scene, PRDP against the converged baseline (means over the seeds)."""
    lines = ["| scene | K_eps | PRDP's final K | metric / baseline (seeds' range) | inner iterations | wall time "
             "| wall-time saving / iteration saving | IC / PR savings |",
             "|---|---|---|---|---|---|---|---|"]
    for name, r in results["scenes"].items():
        spread = [x["final_metric"] for x in r["ratios_per_seed"]]
        finals = sorted({p["k_schedule"][-1][1] for p in r["prdp"]})
        sweep = r.get("sweep", {}).get("savings")
        split = "" if sweep is None else f"{100 * sweep['ic_savings']:.0f}% / {100 * sweep['pr_savings']:.0f}%"
        share = r["wall_time_savings"] / r["iteration_savings"] if r["iteration_savings"] > 0 else float("nan")
        lines.append(f"| `{name}` | {r['k_eps']} | {', '.join(map(str, finals))} | {r['ratios']['final_metric']:.2f}x "
                     f"({min(spread):.2f}-{max(spread):.2f}) | {r['ratios']['total_iterations']:.2f}x "
                     f"| {r['ratios']['wall_time']:.2f}x | {share:.2f} | {split} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=None,
                                 quick="heat-emulator-2d, seed 0 (explicit flags still win)")
    parser.add_argument("--scenes", type=comma_list(str), default=None, help="default: the PRDP scenes")
    parser.add_argument("--seeds", type=comma_list(int), default=None, help="default 0,1,2")
    parser.add_argument("--sweep", type=comma_list(str), default=[],
                        help="scenes to also sweep fixed K for (the IC / PR split)")
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    parser.add_argument("--merge", action="store_true",
                        help="keep the other scenes already in --out (rerun some scenes only) and its other "
                             "records (such as a sweep run by another command)")
    args = parser.parse_args(argv)
    args.scenes = args.scenes or (["heat-emulator-2d"] if args.quick else PRDP_SCENES)
    args.seeds = args.seeds or ([0] if args.quick else [0, 1, 2])
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    # single runs, averaged over the seeds
    with bench_common.report(__file__, args.out, statistic="mean", repeats=1, scenes={}) as results:
        if args.merge and args.out.exists():
            keep_previous(results, json.loads(args.out.read_text()), args.scenes)
        run_scenes(args, results)
    print(markdown_table(results))
    s = results["summary"]
    print(f"mean over {len(s['scenes'])} scenes: {100 * s['mean_iteration_savings']:.0f}% fewer inner iterations, "
          f"{100 * s['mean_wall_time_savings']:.0f}% less wall time; wrote {args.out}")
    return 0


def keep_previous(results: bench_common.Report, previous: dict, rerun: list) -> None:
    """--merge: the scenes not rerun, with the machine and load of their runs, and the other records."""
    results["scenes"] = {n: r for n, r in previous["scenes"].items() if n not in rerun}
    if results["scenes"]:
        results["machine_of_kept_scenes"] = previous.get("machine_of_kept_scenes", previous["machine"])
        results["load"]["kept_scenes"] = previous["load"].get("kept_scenes", previous["load"])
    results.update({k: v for k, v in previous.items()
                    if k not in (*bench_common.REPORT_KEYS, "scenes", "summary", "machine_of_kept_scenes")})


def run_scenes(args, results: bench_common.Report) -> None:
    for name in args.scenes:
        results["scenes"][name] = r = bench_scene(name, args.seeds, name in args.sweep)
        ratio = r["ratios"]
        metric_spread = [x["final_metric"] for x in r["ratios_per_seed"]]
        steps = f", Newton steps {ratio['newton_steps']:.2f}x" if "newton_steps" in ratio else ""
        print(f"{name}: K_eps {r['k_eps']}; PRDP / converged over seeds {args.seeds}: metric "
              f"{ratio['final_metric']:.2f}x ({min(metric_spread):.2f}-{max(metric_spread):.2f}), iterations "
              f"{ratio['total_iterations']:.2f}x{steps}, wall time {ratio['wall_time']:.2f}x", flush=True)
        done = results["scenes"].values()
        results["summary"] = {
            "scenes": list(results["scenes"]),
            "mean_iteration_savings": statistics.mean(s["iteration_savings"] for s in done),
            "mean_wall_time_savings": statistics.mean(s["wall_time_savings"] for s in done),
            "wall_over_iteration_savings": {n: s["wall_time_savings"] / s["iteration_savings"]
                                            for n, s in results["scenes"].items() if s["iteration_savings"] > 0},
        }
        results.save()


if __name__ == "__main__":
    sys.exit(main())
