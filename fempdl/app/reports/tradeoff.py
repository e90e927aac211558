"""The speed-accuracy trade-off of a scene: fixed caps, the converged baseline, PRDP.

:func:`sweep` trains a scene with fixed caps K = 1, 2, 4, ... below K_eps,
with K_eps itself (the converged baseline) and with PRDP, and
:func:`savings` splits PRDP's saving against the baseline the way the PRDP
paper does:

* K_max: the smallest fixed K whose final validation metric is within
  ``tolerance`` (10%) of the baseline's;
* incomplete-convergence (IC) savings: 1 - cost(K_max) / cost(K_eps), what
  training at K_max from the start would save;
* progressive-refinement (PR) savings: (cost(K_max) - cost(PRDP)) / cost(K_eps),
  what PRDP saves on top by starting low;

so that IC + PR is PRDP's total saving 1 - cost(PRDP) / cost(K_eps). Cost is
cumulative forward + backward inner iterations (and, separately, wall time);
on a Newton scene (a nonlinear PDE) the Newton steps are counted apart too
(``newton_savings``), whichever cap K moves (``[solver] refine``).
:func:`clock_bound` says what the saving can do to the wall time: the parts of the
baseline's time that shrink with the cap (:func:`capped_parts`) bound it.
For tasks trained to a target (``stop_at``), K_max is the smallest fixed K
that reaches it.

:func:`write_report` writes ``tradeoff.json``, ``tradeoff.csv`` and three PNG
plots: the metric per epoch for every run with PRDP's K schedule, the
metric against cumulative iterations and against wall time, and where each
run's wall time went (:func:`plot_time_split`).
"""
from __future__ import annotations

import csv
import json
from pathlib import Path

from fempdl.app.runs import runner
from fempdl.app.runs.files import write_recorded
from fempdl.app.runs.plan import ScenePlan
from fempdl.app.runs.result import RunResult
from fempdl.app.runs.settings import RunSettings
from fempdl.app.runs.training import TIME_PARTS
from fempdl.app.schema import Scene

__all__ = ["sweep", "savings", "comparison_table", "write_report", "geometric_caps", "summary_lines",
           "time_split", "plot_time_split", "clock_bound", "capped_parts"]


def geometric_caps(k_eps: int) -> list[int]:
    """1, 2, 4, ... below K_eps."""
    ks, k = [], 1
    while k < k_eps:
        ks.append(k)
        k *= 2
    return ks


def sweep(scene: Scene | ScenePlan, *, ks: list[int] | None = None, out_dir: Path | None = None,
          progress: bool = False, overwrite: bool = False) -> dict[str, RunResult]:
    """Train ``scene`` (or a plan of it, :class:`~fempdl.app.runs.plan.ScenePlan`, whose checked caps
    the runs take) with every fixed K, the converged baseline and PRDP (``overwrite``: replace the runs
    of an earlier sweep in ``out_dir``, which is refused otherwise)."""
    plan = ScenePlan.resolve(scene)
    common = RunSettings(progress=progress, overwrite=overwrite, parallel=plan.parallel)
    baseline = runner.train(plan, plan.caps("converged"), common, out_dir=_sub(out_dir, "converged"))
    keps = baseline.k_eps
    plan = plan.measured(keps, baseline.converged_caps)     # the baseline's, not measured again
    runs = {}
    for k in ks or geometric_caps(keps):
        runs[f"K={k}"] = runner.train(plan, plan.caps("fixed", k), common, out_dir=_sub(out_dir, f"k{k}"))
    runs[f"K_eps={keps}"] = baseline
    runs["PRDP"] = runner.train(plan, plan.caps("prdp"), common, out_dir=_sub(out_dir, "prdp"))
    return runs


def savings(runs: dict[str, RunResult], tolerance: float = 0.1, stop_at: float | None = None,
            refine: str | None = None) -> dict:
    """K_max and the IC / PR / total savings of PRDP against the converged baseline, and the clock's
    bound (:func:`clock_bound`; ``refine``: the scene's ``[solver] refine``, None on a linear PDE)."""
    baseline = next(r for r in runs.values() if r.mode == "converged")
    prdp = next(r for r in runs.values() if r.mode == "prdp")
    fixed = sorted((r for r in runs.values() if r.mode == "fixed"), key=lambda r: r.rows[0]["k"])

    def good_enough(run: RunResult) -> bool:
        if stop_at is not None:
            return run.final_metric <= stop_at
        return run.final_metric <= (1.0 + tolerance) * baseline.final_metric

    k_max_run = next((r for r in fixed if good_enough(r)), baseline)
    cost = baseline.total_iterations
    out = {
        "k_eps": baseline.k_eps,
        "k_max_sweep": k_max_run.rows[0]["k"],
        "k_max_prdp": prdp.rows[-1]["k"],
        "baseline_final_metric": baseline.final_metric,
        "prdp_final_metric": prdp.final_metric,
        "prdp_metric_ratio": prdp.final_metric / baseline.final_metric,
        "ic_savings": 1.0 - k_max_run.total_iterations / cost,
        "pr_savings": (k_max_run.total_iterations - prdp.total_iterations) / cost,
        "total_savings": 1.0 - prdp.total_iterations / cost,
        "wall_time_savings": 1.0 - prdp.wall_time / baseline.wall_time,
        "tolerance": tolerance,
    }
    if baseline.newton_steps:
        out["newton_savings"] = 1.0 - prdp.newton_steps / baseline.newton_steps
    out.update(clock_bound(baseline, out["total_savings"], refine, out.get("newton_savings", 0.0)))
    return out


def capped_parts(refine: str | None) -> tuple[str, ...]:
    """The parts of the time split (:data:`TIME_PARTS`) that shrink with the cap K: the solver's
    iterations; where K moves the Newton cap (``refine`` "newton" or "both") also the assembly and
    set-up, which every Newton step repeats (its Jacobian and residual, its inner solve's set-up).
    With ``refine = "inner"`` the Newton steps, and so those, stay as converged solves need."""
    return ("iterations", "setup", "assembly") if refine in ("newton", "both") else ("iterations",)


def clock_bound(baseline: RunResult, iteration_savings: float, refine: str | None = None,
                newton_savings: float = 0.0) -> dict:
    """What the cap's saving can do to the wall time on this scene and machine, from the baseline's
    time split: only the :func:`capped_parts` shrink with the cap, so the wall time falls by at most
    their share s of the baseline's time (``max_wall_time_savings``, all of them saved), and by each
    part's share times its saving (the iterations' by ``iteration_savings``, assembly and set-up by
    ``newton_savings``) if everything else (network, validation, the rest) costs what it did."""
    split, wall = time_split(baseline), baseline.wall_time
    parts = capped_parts(refine)
    share = {part: split[part] / wall if wall > 0 else 0.0 for part in parts}
    predicted = sum(value * (iteration_savings if part == "iterations" else newton_savings)
                    for part, value in share.items())
    return {"solver_share": sum(share.values()), "max_wall_time_savings": sum(share.values()),
            "predicted_wall_time_savings": predicted, "capped_parts": list(parts)}


def comparison_table(runs: dict[str, RunResult]) -> str:
    """Text table: K schedule, final metric, iterations and time against the converged baseline."""
    baseline = next((r for r in runs.values() if r.mode == "converged"), None)
    newton = any(r.newton_steps is not None for r in runs.values())
    steps = f" {'newton steps':>12}" if newton else ""
    header = (f"{'run':<14} {'K schedule':<26} {'final metric':>12} {'inner its':>11}{steps} {'wall s':>7} "
              f"{'its vs base':>11} {'time vs base':>12}")
    lines = [header, "-" * len(header)]
    for label, r in runs.items():
        schedule = _schedule_text(r.k_schedule)
        rel_its = rel_time = ""
        if baseline is not None:
            rel_its = f"{r.total_iterations / baseline.total_iterations:.2f}x"
            rel_time = f"{r.wall_time / baseline.wall_time:.2f}x"
        steps = f" {r.newton_steps or 0:>12,d}" if newton else ""
        lines.append(f"{label:<14} {schedule:<26} {r.final_metric:>12.3e} {r.total_iterations:>11,d}{steps} "
                     f"{r.wall_time:>7.1f} {rel_its:>11} {rel_time:>12}")
    return "\n".join(lines)


def write_report(scene: Scene, runs: dict[str, RunResult], split: dict, out_dir: Path) -> list[Path]:
    """tradeoff.json, tradeoff.csv and the PNG plots in ``out_dir``; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    summary = {
        "scene": scene.as_dict(),
        "savings": split,
        "runs": {label: {"mode": r.mode, "k_schedule": r.k_schedule, "final_metric": r.final_metric,
                         "total_iterations": r.total_iterations, "newton_steps": r.newton_steps,
                         "wall_time": r.wall_time, "rows": r.rows}
                 for label, r in runs.items()},
    }
    paths = [out_dir / "tradeoff.json", out_dir / "tradeoff.csv", out_dir / "metric_per_epoch.png",
             out_dir / "metric_vs_cost.png", out_dir / "time_split.png"]
    write_recorded(paths[0], lambda p: p.write_text(json.dumps(summary, indent=1)))

    newton = any(r.newton_steps is not None for r in runs.values())

    def write_csv(p: Path) -> None:
        with p.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["run", "mode", "k_schedule", "final_metric", "total_iterations", "wall_time",
                             *(f"time_{part}" for part in TIME_PARTS), *(["newton_steps"] if newton else [])])
            for label, r in runs.items():
                writer.writerow([label, r.mode, _schedule_text(r.k_schedule), r.final_metric,
                                 r.total_iterations, r.wall_time, *time_split(r).values(),
                                 *([r.newton_steps] if newton else [])])
    write_recorded(paths[1], write_csv)
    _plot_per_epoch(runs, paths[2], scene.name)
    _plot_against_cost(runs, paths[3], scene.name)
    plot_time_split(runs, paths[4], scene.name)
    return paths


def time_split(run: RunResult) -> dict[str, float]:
    """Seconds of the run's wall time per part (:data:`fempdl.app.runs.training.TIME_PARTS`)."""
    last = run.rows[-1]
    return {part: float(last.get(f"time_{part}", 0.0)) for part in TIME_PARTS}


def plot_time_split(runs: dict[str, RunResult], path: Path, title: str) -> None:
    """A stacked bar per run: its wall time split into solver iterations, set-up,
    assembly, adjoint operator, network, validation and the rest."""
    from matplotlib.figure import Figure  # drawn without pyplot: the caller's backend stays as it is

    labels = list(runs)
    fig = Figure(figsize=(max(5.0, 1.2 * len(labels) + 3.0), 5))
    ax = fig.subplots()
    bottom = [0.0] * len(labels)
    for part in TIME_PARTS:
        heights = [time_split(runs[label])[part] for label in labels]
        ax.bar(labels, heights, bottom=bottom, label=part.replace("_", " "))
        bottom = [b + h for b, h in zip(bottom, heights)]
    ax.set_ylabel("wall time [s]")
    ax.set_title(f"{title}: where the training time went")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    for tick in ax.get_xticklabels():
        tick.set_rotation(20)
        tick.set_horizontalalignment("right")
    fig.tight_layout()
    write_figure(fig, path)


def _schedule_text(schedule: list[tuple[int, int]]) -> str:
    ks = [str(k) for _, k in schedule]
    return ks[0] if len(ks) == 1 else (" ".join(ks) if len(ks) <= 6 else " ".join(ks[:3] + ["..."] + ks[-2:]))


def _sub(out_dir: Path | None, name: str) -> Path | None:
    return None if out_dir is None else Path(out_dir) / name


def _plot_per_epoch(runs: dict[str, RunResult], path: Path, title: str) -> None:
    from matplotlib.figure import Figure  # drawn without pyplot: the caller's backend stays as it is

    fig = Figure(figsize=(8, 5))
    ax = fig.subplots()
    for label, r in runs.items():
        style = {"linewidth": 2.5, "color": "black"} if r.mode == "prdp" else {"linewidth": 1.2}
        ax.semilogy([row["epoch"] for row in r.rows], [row["val_metric"] for row in r.rows], label=label, **style)
    ax.set_xlabel("epoch")
    ax.set_ylabel("validation metric")
    ax.set_title(f"{title}: validation metric per epoch")
    prdp = runs.get("PRDP")
    if prdp is not None:
        twin = ax.twinx()
        twin.step([row["epoch"] for row in prdp.rows], [row["k"] for row in prdp.rows], where="post",
                  color="tab:red", linestyle="--", label="PRDP K")
        twin.set_ylabel("PRDP's K", color="tab:red")
    ax.legend(fontsize=8, loc="upper right")
    fig.tight_layout()
    write_figure(fig, path)


def _plot_against_cost(runs: dict[str, RunResult], path: Path, title: str) -> None:
    from matplotlib.figure import Figure  # drawn without pyplot: the caller's backend stays as it is

    fig = Figure(figsize=(12, 5))
    axes = fig.subplots(1, 2, sharey=True)
    for label, r in runs.items():
        style = {"linewidth": 2.5, "color": "black"} if r.mode == "prdp" else {"linewidth": 1.2}
        metric = [row["val_metric"] for row in r.rows]
        axes[0].loglog([max(row["total_iterations"], 1) for row in r.rows], metric, label=label, **style)
        axes[1].semilogy([row["wall_time"] for row in r.rows], metric, label=label, **style)
    axes[0].set_xlabel("cumulative inner iterations (forward + backward)")
    axes[1].set_xlabel("training wall time [s]")
    axes[0].set_ylabel("validation metric")
    axes[0].legend(fontsize=8)
    fig.suptitle(f"{title}: error against cost")
    fig.tight_layout()
    write_figure(fig, path)


def summary_lines(split: dict) -> list[str]:
    return [
        f"K_eps = {split['k_eps']}, K_max from the sweep = {split['k_max_sweep']}, "
        f"PRDP's final K = {split['k_max_prdp']}",
        f"PRDP final metric {split['prdp_final_metric']:.3e} = {split['prdp_metric_ratio']:.2f}x the converged "
        f"baseline's {split['baseline_final_metric']:.3e}",
        f"inner-iteration savings against the baseline: total {100 * split['total_savings']:.0f}% = "
        f"IC {100 * split['ic_savings']:.0f}% + PR {100 * split['pr_savings']:.0f}%; "
        f"wall time {100 * split['wall_time_savings']:.0f}%",
        f"the clock: {_parts_text(split)} {100 * split['solver_share']:.0f}% of the baseline's time, so "
        f"PRDP can save at most {100 * split['max_wall_time_savings']:.0f}% of the wall time here; its "
        f"{'savings predict' if len(split.get('capped_parts', ())) > 1 else 'iteration saving predicts'} "
        f"{100 * split['predicted_wall_time_savings']:.0f}%, it reached {100 * split['wall_time_savings']:.0f}%"
        + (" (past the bound: costs the cap does not move differ between the runs, such as start-up costs the "
           "baseline pays as the first run, or other load on the machine)"
           if round(100 * split["wall_time_savings"]) > round(100 * split["max_wall_time_savings"]) else ""),
    ] + ([f"Newton steps: {100 * split['newton_savings']:.0f}% fewer than the baseline's"]
         if "newton_savings" in split else [])


def _parts_text(split: dict) -> str:
    """What the clock's bound counts, for the summary line (splits written before list no parts)."""
    if len(split.get("capped_parts", ())) > 1:
        return "the solver's iterations and the Newton steps' assembly and set-up are"
    return "the solver's iterations are"


def write_figure(fig, path: Path) -> None:
    """Write ``fig`` (a matplotlib Figure) as a PNG atomically: an interrupted write leaves no half file."""
    write_recorded(path, lambda p: fig.savefig(p, format="png", dpi=120))
