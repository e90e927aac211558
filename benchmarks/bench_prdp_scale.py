"""Benchmark: where PRDP's iteration saving reaches the clock, against the size of the heat emulator.

The PRDP paper's appendix states the rule: on small systems other work
(the network, validation, bookkeeping) holds most of a training step, so
fewer solver iterations hardly shorten it; as the system grows the solver's
share of the time grows, and the wall-time saving converges to the iteration
saving. This script measures that curve on fempdl's heat emulators (2D
L-shape and 3D unit cube, P1) at several mesh sizes, with the same network,
data, epochs and PRDP rule at every size, so that only the size moves:

- the graph network of the scenes (its cost is linear in the DOFs, like one
  solver iteration's), ``--hidden`` channels, ``--layers`` convolutions; and
  in 2D also the 2D scene's residual MLP (``2d-mlp``, width 64: linear in the
  DOFs too, about ten times cheaper per DOF);
- 2D: Richardson + Jacobi, the paper's solver and the 2D scene's (K_eps grows
  like 1/h^2, i.e. like the DOFs); 3D: CG + Jacobi, because Richardson +
  Jacobi diverges on the finer tetrahedral meshes (the Jacobi-preconditioned
  operator's largest eigenvalue exceeds 2 there; K_eps grows like 1/h, i.e.
  like DOFs^(1/3));
- PRDP from ``k0 = ceil(K_eps / --k0-fraction)``, refined by
  ``max(K + 1, ceil(--growth K))`` up to K_eps: the same rule relative to the
  converged cap at every size (a fixed k0 and dk would mean a different
  schedule on a 30-iteration and a 2,000-iteration solver).

For each size and each seed (network initialisation and minibatch order; the
data are the scene's) one converged run (every step at K_eps) and one PRDP run,
one after the other, so both see the same machine load. Recorded per size: the
DOFs, K_eps, the solver's share of the baseline's wall time (its iterations'
time over its wall time), the iteration saving, the wall-time saving, their
ratio, the wall saving the share predicts (share x iteration saving, if
nothing else changed) and the metric ratio (PRDP / baseline, mean over the
seeds, and each seed's). Wall times are the training epochs' (validation
included), not the set-up (meshing, reference data, K_eps).

Writes ``bench-results/bench_prdp_scale.json`` (``--out``, through
``bench_common.report``: single runs, statistic "mean" over the seeds) after every run,
and resumes from it (a size and seed already recorded is not rerun), and a
plot of the curve beside it (``.png``). Run on an idle machine with one
thread: ``python benchmarks/bench_prdp_scale.py --threads 1``; ``--quick`` runs
two small sizes per dimension for a smoke test.
"""
from __future__ import annotations

import json
import math
import statistics
import sys
from pathlib import Path

import torch
from bench_scenes import summary

from fempdl.app import scene
from fempdl.app.runs import runner

import bench_common
from bench_common import comma_list

# Per dimension: the bundled scene, what changes in it, and the mesh sizes (about 1.5k to 150k DOFs).
DIMENSIONS = {
    "2d": {"scene": "heat-emulator-2d", "set": ["solver.preset=jacobi"], "h": [0.05, 0.025, 0.0125, 0.007]},
    "3d": {"scene": "heat-emulator-3d", "set": ["solver.preset=cg"], "h": [0.1, 0.05, 0.03, 0.017]},
    # The 2D scene's own network, a residual MLP of width 64: also linear in the DOFs, about ten
    # times cheaper per DOF than the graph network.
    "2d-mlp": {"scene": "heat-emulator-2d", "set": ["solver.preset=jacobi", "network.type=mlp",
                                                    "network.hidden=64", "network.layers=2"],
               "h": [0.05, 0.025, 0.0125, 0.007]},
}
QUICK_H = {"2d": [0.08, 0.05], "3d": [0.15, 0.1], "2d-mlp": [0.08]}


def common_settings(args) -> list[str]:
    """What every size shares: network, data, optimizer, stopping rule (the epochs)."""
    return ["network.type=graph", f"network.hidden={args.hidden}", f"network.layers={args.layers}",
            f"data.train={args.train}", f"data.validation={args.validation}", f"optimizer.batch={args.batch}",
            f"optimizer.epochs={args.epochs}", "solver.warm_start=true"]


def prdp_settings(k_eps: int, args) -> list[str]:
    """PRDP's rule relative to the converged cap: start at K_eps / k0_fraction, grow by ``growth``."""
    k0 = max(1, math.ceil(k_eps / args.k0_fraction))
    return [f"prdp.k0={k0}", "prdp.dk=1", f"prdp.growth={args.growth}", f"prdp.k_cap={max(k_eps, k0)}"]


def dofs_of(sc) -> int:
    """The heat problem's unknowns on the scene's mesh (built once per size; cheap next to training)."""
    task = runner.build_task(sc, runner.layer_options(sc, 1))
    try:
        return int(task.problem.output_size)
    finally:
        task.close()


def size_summary(entry: dict) -> dict:
    """The curve's point of one size from its seeds' runs (means over the seeds)."""
    base, prdp = entry["converged"], entry["prdp"]
    mean = lambda runs, key: statistics.mean(r[key] for r in runs)      # noqa: E731
    share = statistics.mean(r["time_split"]["iterations"] / r["wall_time"] for r in base)
    iteration_savings = 1.0 - mean(prdp, "total_iterations") / mean(base, "total_iterations")
    wall_savings = 1.0 - mean(prdp, "wall_time") / mean(base, "wall_time")
    return {"dofs": entry["dofs"], "k_eps": entry["k_eps"], "seeds": len(base), "solver_share": share,
            "iteration_savings": iteration_savings, "wall_time_savings": wall_savings,
            "wall_over_iteration_savings": wall_savings / iteration_savings if iteration_savings > 0 else None,
            "predicted_wall_time_savings": share * iteration_savings,
            "metric_ratio": mean(prdp, "final_metric") / mean(base, "final_metric"),
            "metric_ratio_per_seed": [p["final_metric"] / b["final_metric"] for p, b in zip(prdp, base)],
            "wall_seconds_converged": mean(base, "wall_time"), "wall_seconds_prdp": mean(prdp, "wall_time")}


def bench_size(dim: str, h: float, args, results: bench_common.Report) -> None:
    spec = DIMENSIONS[dim]
    key = f"{dim}/h={h:g}"
    entry = results["sizes"].setdefault(key, {"dim": dim, "h": h, "converged": [], "prdp": [], "seeds": []})
    settings = common_settings(args) + spec["set"] + [f"mesh.h={h}"]
    base_scene = scene.load(spec["scene"], settings)
    if "dofs" not in entry:
        entry["dofs"] = dofs_of(base_scene)
    for seed in args.seeds:
        if seed in entry["seeds"]:
            continue
        b = runner.run(base_scene, "converged", seed=seed, k_eps_value=entry.get("k_eps"))
        entry["k_eps"] = b.k_eps
        prdp_scene = scene.load(spec["scene"], settings + prdp_settings(b.k_eps, args))
        p = runner.run(prdp_scene, "prdp", seed=seed, k_eps_value=b.k_eps)
        entry["converged"].append(summary(b))
        entry["prdp"].append(summary(p))
        entry["seeds"].append(seed)
        entry["summary"] = point = size_summary(entry)
        results.save()
        print(f"{key} ({entry['dofs']} DOFs, K_eps {b.k_eps}) seed {seed}: solver share "
              f"{point['solver_share']:.2f}, iterations -{100 * point['iteration_savings']:.0f}%, wall "
              f"-{100 * point['wall_time_savings']:.0f}%, metric {point['metric_ratio']:.2f}x", flush=True)


def markdown_table(results: dict) -> str:
    """The table of docs/scenes.md: one row per dimension and size, means over the seeds."""
    lines = ["| heat emulator | DOFs | K_eps | solver's share | iteration saving | wall saving "
             "| wall / iteration saving | share x iteration saving | metric / baseline (seeds' range) |",
             "|---|---|---|---|---|---|---|---|---|"]
    for entry in sorted(results["sizes"].values(), key=lambda e: (e["dim"], e.get("dofs", 0))):
        s = entry.get("summary")
        if s is None:
            continue
        ratio = "" if s["wall_over_iteration_savings"] is None else f"{s['wall_over_iteration_savings']:.2f}"
        lines.append(f"| {entry['dim']} | {s['dofs']:,} | {s['k_eps']} | {s['solver_share']:.2f} "
                     f"| {100 * s['iteration_savings']:.0f}% | {100 * s['wall_time_savings']:.0f}% | {ratio} "
                     f"| {100 * s['predicted_wall_time_savings']:.0f}% | {s['metric_ratio']:.2f}x "
                     f"({min(s['metric_ratio_per_seed']):.2f}-{max(s['metric_ratio_per_seed']):.2f}) |")
    return "\n".join(lines)


def plot(results: dict, path: Path) -> None:
    """Solver share, iteration saving and wall saving against the DOFs, one panel per dimension."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    dims = sorted({e["dim"] for e in results["sizes"].values() if "summary" in e})
    fig, axes = plt.subplots(1, len(dims), figsize=(5.5 * len(dims), 4), squeeze=False)
    for ax, dim in zip(axes[0], dims):
        points = sorted((e["summary"] for e in results["sizes"].values() if e["dim"] == dim and "summary" in e),
                        key=lambda s: s["dofs"])
        x = [s["dofs"] for s in points]
        for field, label, style in (("solver_share", "solver's share of the baseline's time", "k--"),
                                    ("iteration_savings", "iteration saving", "o-"),
                                    ("wall_time_savings", "wall-time saving", "s-")):
            ax.plot(x, [s[field] for s in points], style, label=label)
        ax.set_xscale("log")
        ax.set_ylim(0.0, 1.0)
        ax.set_xlabel("DOFs")
        ax.set_title(f"heat emulator {dim.upper()}: PRDP against the converged cap")
        ax.grid(True, alpha=0.3)
        ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=None,
                                 quick="two small sizes per dimension")
    parser.add_argument("--dims", type=comma_list(str), default=list(DIMENSIONS), help=f"of {list(DIMENSIONS)}")
    parser.add_argument("--h", type=comma_list(float), help="mesh sizes (default: each dimension's own)")
    parser.add_argument("--seeds", type=comma_list(int), default=[0, 1, 2])
    parser.add_argument("--epochs", type=int, default=12)
    parser.add_argument("--train", type=int, default=32)
    parser.add_argument("--validation", type=int, default=8)
    parser.add_argument("--batch", type=int, default=8)
    parser.add_argument("--hidden", type=int, default=16)
    parser.add_argument("--layers", type=int, default=3)
    parser.add_argument("--k0-fraction", type=float, default=8.0)
    parser.add_argument("--growth", type=float, default=1.5)
    parser.add_argument("--threads", type=int, help="torch threads (default: torch's)")
    args = parser.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    settings = {k: v for k, v in vars(args).items() if k not in ("out", "h", "dims", "seeds", "quick", "repeats")}
    before = json.loads(args.out.read_text()) if args.out.exists() else {}
    if before.get("settings", settings) != settings:
        raise SystemExit(f"{args.out} holds runs with other settings {before['settings']}; pass another --out")
    # single runs, averaged over the seeds
    with bench_common.report(__file__, args.out, statistic="mean", repeats=1, settings=settings,
                             sizes=before.get("sizes", {})) as results:
        if "machine" in before:                         # resumed: the record of the first runs
            results["machine"], results["load"]["start"] = before["machine"], before["load"]["start"]
        for dim in args.dims:
            for h in args.h or (QUICK_H if args.quick else {d: s["h"] for d, s in DIMENSIONS.items()})[dim]:
                bench_size(dim, h, args, results)
    plot(results, args.out.with_suffix(".png"))
    print(markdown_table(results))
    print(f"wrote {args.out} and {args.out.with_suffix('.png')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
