"""A training method against Adam with backpropagation, at equal iterations and at equal training time.

:func:`compare` trains a sip or hig scene twice from the same initial network
(:mod:`fempdl.app.tasks.learned_inverse`): with the scene's method for its epochs, then with
the baseline for as many; if the baseline used less training time (time in
optimizer steps, validation excluded), it is resumed and goes on until it has
used the method's time, at most ``max_factor`` times the iterations.
:func:`summary` gives the ratios method / baseline of the validation metric

* at equal iterations: after the method's last iteration;
* at equal time: the method's final metric against the baseline's at the last
  epoch that ended within the method's training time;

and :func:`write_report` writes ``compare.json``, ``compare.csv`` and
``error_vs_cost.png`` (the metric against iterations and against training
time, one curve per run).
"""
from __future__ import annotations

import csv
import json
import math
from pathlib import Path

from fempdl.app import tasks
from fempdl.app.reports.tradeoff import write_figure
from fempdl.app.runs import rundir, runner
from fempdl.app.runs.files import write_recorded
from fempdl.app.runs.plan import ScenePlan
from fempdl.app.runs.result import RunResult
from fempdl.app.runs.settings import RunSettings
from fempdl.app.schema import Scene

__all__ = ["compare", "compare_and_report", "summary", "summary_lines", "table", "write_report"]

BASELINE = "backprop"


def compare(scene: Scene | ScenePlan, out_dir: Path, *, epochs: int | None = None, equal_time: bool = True,
            max_factor: int = 20, resume: bool = False, progress: bool = False,
            overwrite: bool = False) -> dict[str, RunResult]:
    """Train the scene's method and the baseline (module docstring); runs keyed by method. ``scene``
    may be its plan (:class:`~fempdl.app.runs.plan.ScenePlan`).

    Each run keeps its metrics and checkpoint under ``out_dir``/<method>;
    ``resume`` continues runs that have a checkpoint fempdl wrote and starts the others afresh
    (replacing only files fempdl wrote there); ``overwrite`` replaces the runs' files."""
    out_dir = Path(out_dir)
    plan = ScenePlan.resolve(scene)
    method = tasks.method_of(plan.scene)

    common = RunSettings(progress=progress)

    def train(name: str, **changes) -> RunResult:
        sub = out_dir / name
        again = resume and rundir.can_resume(sub)
        anew = not again and (overwrite or (resume and not rundir.foreign_entries(sub)))
        return runner.train_method(plan, name, common, out_dir=sub, resume=again, overwrite=anew, **changes)

    runs = {method: train(method, epochs=epochs)}
    n = len(runs[method].rows)
    runs[BASELINE] = train(BASELINE, epochs=n)
    budget = runs[method].rows[-1]["train_time"]
    if equal_time and runs[BASELINE].rows[-1]["train_time"] < budget:
        sub = out_dir / BASELINE
        runs[BASELINE] = runner.train_method(plan, BASELINE, common, out_dir=sub, resume=True,
                                             epochs=max_factor * n, stop_at_time=budget)
    return runs


def compare_and_report(scene: Scene | ScenePlan, out_dir: Path, *, equal_time: bool = True, resume: bool = False,
                       progress: bool = False, overwrite: bool = False
                       ) -> tuple[dict[str, RunResult], dict, list[Path]]:
    """:func:`compare`, :func:`summary` and :func:`write_report` into ``out_dir``: (runs, summary, paths)."""
    plan = ScenePlan.resolve(scene)
    runs = compare(plan, out_dir, equal_time=equal_time, resume=resume, progress=progress, overwrite=overwrite)
    split = summary(plan.scene, runs, equal_time=equal_time)
    return runs, split, write_report(plan.scene, runs, split, out_dir)


def steps_per_epoch(scene: Scene) -> int:
    return math.ceil(scene.data.train / scene.optimizer.batch)


def summary(scene: Scene, runs: dict[str, RunResult], equal_time: bool = True) -> dict:
    """Ratios method / baseline of the validation metric at equal iterations and at equal training time.

    The equal-time entries are None without ``equal_time`` (the baseline was not
    extended) or when the baseline's first epoch already took longer than the
    method's whole run; ``baseline_reached_time`` is False when the baseline
    stopped at its iteration cap before using the method's time."""
    method = tasks.method_of(scene)
    ours, base = runs[method].rows, runs[BASELINE].rows
    n = min(len(ours), len(base))
    budget = ours[-1]["train_time"]
    within = [row for row in base if row["train_time"] <= budget] if equal_time else []
    steps = steps_per_epoch(scene)
    return {
        "method": method, "metric": "x error" if scene.task == "sip" else "observation nMSE",
        "iterations": n * steps,
        "method_metric": ours[n - 1]["val_metric"], "baseline_metric": base[n - 1]["val_metric"],
        "ratio_equal_iterations": ours[n - 1]["val_metric"] / base[n - 1]["val_metric"],
        "equal_time_seconds": budget,
        "baseline_iterations_in_that_time": len(within) * steps,
        "baseline_reached_time": base[-1]["train_time"] >= budget,
        "baseline_metric_at_equal_time": within[-1]["val_metric"] if within else None,
        "ratio_equal_time": ours[-1]["val_metric"] / within[-1]["val_metric"] if within else None,
        "seconds_per_iteration": {name: r.rows[-1]["train_time"] / (len(r.rows) * steps) for name, r in runs.items()},
    }


def table(scene: Scene, runs: dict[str, RunResult]) -> str:
    """Text table of the runs: iterations, final metric, training time, against the baseline."""
    base = runs.get(BASELINE)
    steps = steps_per_epoch(scene)
    header = f"{'run':<10} {'iterations':>10} {'final metric':>12} {'train s':>8} {'final vs base':>14} {'s/it':>8}"
    lines = [header, "-" * len(header)]
    for name, r in runs.items():
        iterations, seconds = len(r.rows) * steps, r.rows[-1]["train_time"]
        ratio = "" if base is None else f"{r.final_metric / base.final_metric:.3f}x"
        lines.append(f"{name:<10} {iterations:>10,d} {r.final_metric:>12.3e} {seconds:>8.1f} {ratio:>14} "
                     f"{seconds / iterations:>8.4f}")
    return "\n".join(lines)


def summary_lines(split: dict) -> list[str]:
    name = split["method"].upper()
    lines = [f"after {split['iterations']} iterations each: {name} {split['metric']} {split['method_metric']:.3e}, "
             f"Adam + backprop {split['baseline_metric']:.3e}: ratio {split['ratio_equal_iterations']:.3f}"]
    if split["ratio_equal_time"] is None:
        lines.append("no comparison at equal training time (the baseline was not run to the method's time, or "
                     "its first epoch took longer than the method's whole run)")
        return lines
    capped = "" if split["baseline_reached_time"] else ", the baseline stopped at its iteration cap before"
    lines.append(f"at equal training time ({split['equal_time_seconds']:.1f} s, "
                 f"{split['baseline_iterations_in_that_time']} baseline iterations{capped}): "
                 f"{name} / Adam + backprop = {split['ratio_equal_time']:.3f}")
    return lines


def write_report(scene: Scene, runs: dict[str, RunResult], split: dict, out_dir: Path) -> list[Path]:
    """compare.json, compare.csv and error_vs_cost.png in ``out_dir``; returns the paths."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = [out_dir / "compare.json", out_dir / "compare.csv", out_dir / "error_vs_cost.png"]
    report = {"scene": scene.as_dict(), "summary": split,
              "runs": {name: {"final_metric": r.final_metric, "rows": r.rows} for name, r in runs.items()}}
    write_recorded(paths[0], lambda p: p.write_text(json.dumps(report, indent=1)))

    def write_csv(p: Path) -> None:
        with p.open("w", newline="") as fh:
            writer = csv.writer(fh)
            writer.writerow(["run", "iteration", "val_metric", "train_loss", "train_time"])
            for name, r in runs.items():
                for row in r.rows:
                    writer.writerow([name, (row["epoch"] + 1) * steps_per_epoch(scene), row["val_metric"],
                                     row["train_loss"], row["train_time"]])
    write_recorded(paths[1], write_csv)
    _plot(scene, runs, split, paths[2])
    return paths


def _plot(scene: Scene, runs: dict[str, RunResult], split: dict, path: Path) -> None:
    from matplotlib.figure import Figure  # drawn without pyplot: the caller's backend stays as it is

    steps = steps_per_epoch(scene)
    fig = Figure(figsize=(12, 5))
    axes = fig.subplots(1, 2, sharey=True)
    for name, r in runs.items():
        label = "Adam + backprop" if name == BASELINE else f"{name.upper()}"
        style = {"color": "black", "linewidth": 2.0} if name != BASELINE else {"color": "tab:blue", "linewidth": 1.2}
        metric = [row["val_metric"] for row in r.rows]
        axes[0].loglog([(row["epoch"] + 1) * steps for row in r.rows], metric, label=label, **style)
        axes[1].semilogy([row["train_time"] for row in r.rows], metric, label=label, **style)
    axes[0].axvline(split["iterations"], color="gray", linestyle=":", linewidth=1)
    if split["ratio_equal_time"] is not None:
        axes[1].axvline(split["equal_time_seconds"], color="gray", linestyle=":", linewidth=1)
    axes[0].set_xlabel("training iterations")
    axes[1].set_xlabel("training time [s] (optimizer steps, validation excluded)")
    axes[0].set_ylabel(f"validation {split['metric']}")
    axes[0].legend()
    fig.suptitle(f"{scene.name}: {split['method'].upper()} against Adam with backpropagation")
    fig.tight_layout()
    write_figure(fig, path)
