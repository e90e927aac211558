"""Benchmark: PRDP against converged solves in training loops written as users write them.

Each setting is a hand-written loop (no scene, no CLI), trained twice per seed
with the same data, network initialisation and batches:

* ``converged``: the cap at K_eps, what converged solves of the loop's
  validation inputs need from zero (:func:`fempdl.prdp.k_eps`, or
  ``newton_k_eps``); a Newton solve stops at its tolerance before it;
* ``prdp``: :class:`fempdl.PRDP` stepped on the loop's validation metric with
  the README's rule refined geometrically (``growth=1.5``: as many refinements
  from k0 to K_eps whatever K_eps is), from ``k0 = k_start(...)`` (the first cap
  within 50% of converged solves from zero) up to ``k_cap = K_eps``, its health
  check on (the default: a training call whose capped solve did not shrink its
  residual refines at once);
* ``prdp-strict`` (the Newton inverse settings, ``--strict``): the same with k0
  within 1% of converged solves, the tolerance a fit to a relative misfit of
  1e-4 allows (a relative solution error e moves such a loss by about e^2).

Settings:

* ``readme``: the README's loop (a network maps 8 amplitudes to a source,
  -div grad u = f on the L-shape, Richardson + Jacobi from zero);
* ``warm-linear``: a heat-step emulator (a residual network advances u0 -> u1,
  a capped heat step u1 -> u2 warm-started from u1, the loss against two
  converged steps);
* ``newton-cold`` / ``newton-warm``: an inverse problem through Newton solves: a
  coordinate MLP gives kappa(x) in the regularised p-Laplacian
  -div(kappa (1e-4 + |grad u|^2)^(1/2) grad u) = f for 4 sources, 40 point
  sensors, Adam, LU inner solves; from zero, or from the previous step's states
  (the metric PRDP steps on is the training loss, as such a loop has no
  validation set);
* ``nonlinear-heat``: the emulator through one backward-Euler step of
  -div((1 + 20 u^2) grad u), Newton warm-started from u1;
* ``ddp``: ``warm-linear`` under torchrun with its gradients all-reduced over 2
  processes (gloo), each solving its shard, the metric all-reduced.

Both modes validate every epoch at reference physics (LU; a converged Newton):
PRDP steps on the validation as a function (``ctrl.step(loop.metric)``), which it
runs converged, and at the caps where its rule would hold (the gap rule); the
converged loop runs the same validation. The wall time includes it.

* ``readme-as-written``: the README's loop itself (the bundled L-shape, 1.5k
  DOFs, 64 samples in one batch, 200 epochs), with the README's caps (k0 from
  ``k_start``, ``k_cap`` = K_eps to 1e-6, growth 1.5).

The loops themselves are in ``prdp_loops_cases.py``; this script trains them and records the runs.

Recorded per run: the metric at the end evaluated with converged solves, Newton
steps and inner iterations (forward + backward, training and validation, all
ranks), the training wall time and the K schedule; per setting the means over
the seeds and the ratios PRDP / converged. The loops of a few seconds run ``--repeats``
(5) times (the same numbers but the wall time, whose median is kept,
``bench_common.repeat_runs``: their ratio moved by 0.92-1.02x from one run to
the next). Writes ``bench-results/bench_prdp_loops.json`` (``--out``, through
``bench_common.report``, with the load after every run) after every run and resumes
from it. Run on an idle machine: ``python benchmarks/bench_prdp_loops.py``;
``--quick`` runs one seed of shortened loops.
"""
from __future__ import annotations

import argparse
import functools
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI  # noqa: F401  (PyPI's DOLFINx, which prdp_loops_cases loads, needs it first)
import torch
import torch.distributed as dist
from prdp_loops_cases import all_reduce, build

from fempdl import PRDP
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.prdp import k_eps, k_start, newton_k_eps, reference_physics

import bench_common
from bench_common import comma_list

SETTINGS = ("readme-as-written", "readme", "warm-linear", "hole-emulator", "newton-cold", "newton-warm",
            "nonlinear-heat", "newton-rollout", "ddp")
STRICT = ()
REPEATED = ("warm-linear", "ddp")         # loops of a few seconds: run --repeats times
K0_TOLERANCE = {"prdp": None, "prdp-strict": 0.01}    # None: k_start's default (by what the capped gradient is)
EPOCHS = {"readme-as-written": 200, "hole-emulator": 60, "newton-rollout": 80, "readme": 60, "warm-linear": 60,
          "newton-cold": 300, "newton-warm": 300, "nonlinear-heat": 40, "ddp": 60}
# How the runs validate: at reference physics (PRDP steps on a function it runs converged; the converged loop
# runs the same validation). Runs recorded before ("capped") are run again.
VALIDATION = "reference"
# The README's rule, refined geometrically (K -> max(K + 1, ceil(1.5 K))): the same number of
# refinements from k0 to K_eps whether K_eps is 10 or 500 iterations.
PRDP_RULE = dict(dk=1, growth=1.5, tau_step=0.95, tau_stop=0.9, delta=3, ema_window=6)


def caps_for(loop, tolerance: float | None) -> tuple[int, int]:
    """(K0, K_eps): K_eps from zero on the loop's validation inputs, k0 from the starts the loop uses
    (k_start's default tolerance for None); a rollout's both on its own calls at the initial model."""
    if hasattr(loop, "probe"):
        keps = k_eps(loop.caps, rtol=1e-8, call=loop.probe)
        return min(k_start(loop.caps, tolerance=tolerance, k_max=keps, call=loop.probe), keps), keps
    cold = {k: v for k, v in loop.inputs.items() if k != "initial_guess"}
    keps = newton_k_eps(loop.caps, rtol=1e-8, **cold) if isinstance(loop.caps, NewtonCaps) \
        else k_eps(loop.caps, rtol=1e-6, **cold)
    return min(k_start(loop.caps, tolerance=tolerance, k_max=keps, **loop.inputs), keps), keps


def train(setting: str, mode: str, seed: int, epochs: int, rank: int = 0, size: int = 1) -> dict:
    loop = build(setting, seed, rank, size)
    k0, keps = caps_for(loop, K0_TOLERANCE.get(mode))
    ctrl = PRDP(loop.caps, k0=k0, k_cap=keps, **PRDP_RULE) if mode != "converged" else None
    if ctrl is None:
        loop.caps.max_it = keps
    ks = []
    t0 = time.perf_counter()
    for _ in range(epochs):
        loop.epoch()
        ks.append(loop.caps.max_it)
        if ctrl is not None:
            ctrl.step(loop.metric)                  # at reference physics, the capped metric where the rule holds
        else:
            with torch.no_grad(), reference_physics(loop.layers):
                loop.metric()                       # the same validation, at the same cost
    wall = time.perf_counter() - t0
    counts = torch.tensor([float(sum(getattr(s, name, 0) for s in (layer.stats for layer in loop.layers)))
                           for name in ("newton_steps", "backward_newton_steps", "forward_iterations",
                                        "backward_iterations")], dtype=torch.float64)
    counts = all_reduce(counts)
    reference = [layer.reference_stats for layer in loop.layers if layer.reference_stats is not None]
    return {"mode": mode, "seed": seed, "k0": k0, "k_eps": keps, "k_schedule": ks, "wall_time": wall,
            "k_cap_final": keps if ctrl is None else ctrl.k_cap,
            "causes": [] if ctrl is None else [[rec.step, rec.k, rec.cause, rec.gap] for rec in ctrl.history
                                                if rec.refined or rec.gap is not None],
            "reference_time": sum(stats.layer_time for stats in reference),
            "health_refinements": [] if ctrl is None else ctrl.health_refinements,
            "newton_steps": int(counts[0] + counts[1]), "inner_iterations": int(counts[2] + counts[3]),
            **loop.final()}


def train_ddp(mode: str, seed: int, epochs: int) -> dict:
    """Run this script's worker on 2 processes under torchrun; rank 0's result."""
    result = Path(os.environ.get("TMPDIR", "/tmp"), f"bench_prdp_loops_{os.getpid()}.json")
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
               __file__, "--worker", mode, str(seed), str(epochs), str(result)]
    done = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if done.returncode:
        raise RuntimeError(done.stderr[-3000:])
    out = json.loads(result.read_text())
    result.unlink()
    return out


def worker(mode: str, seed: int, epochs: int, result: str) -> None:
    dist.init_process_group("gloo")
    torch.set_num_threads(1)
    out = train("ddp", mode, seed, epochs, dist.get_rank(), dist.get_world_size())
    if dist.get_rank() == 0:
        Path(result).write_text(json.dumps(out))
    dist.destroy_process_group()


def summarise(runs: dict) -> dict:
    by_mode = {mode: [r for r in runs.values() if r["mode"] == mode] for mode in ("converged", *K0_TOLERANCE)}
    by_mode = {mode: rs for mode, rs in by_mode.items() if rs}
    if "converged" not in by_mode or "prdp" not in by_mode:
        return {}
    mean = {mode: {key: statistics.fmean(r[key] for r in rs) for key in
                   ("final_metric", "wall_time", "newton_steps", "inner_iterations")}
            for mode, rs in by_mode.items()}
    base = mean["converged"]
    summary = {"mean": mean}
    for mode in K0_TOLERANCE:
        if mode in mean:
            ratio = {key: (mean[mode][key] / base[key] if base[key] else None) for key in base}
            summary[f"{mode}_over_converged"] = ratio
            summary.setdefault("targets", {})[mode] = {"metric_within_1.05": ratio["final_metric"] <= 1.05,
                                                       "wall_at_most_1.00": ratio["wall_time"] <= 1.0}
    return summary


def main() -> None:
    parser = bench_common.parser(__file__, __doc__.split("\n\n")[0], repeats=5, quick_repeats=1,
                                 quick="one seed, a fifth of the epochs")
    parser.add_argument("--settings", type=comma_list(str), default=list(SETTINGS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--strict", type=comma_list(str), default=list(STRICT),
                        help="settings also run with k0 within 1%% of converged solves")
    parser.add_argument("--worker", nargs=4, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        mode, seed, epochs, result = args.worker
        return worker(mode, int(seed), int(epochs), result)
    torch.set_num_threads(1)
    before = json.loads(args.out.read_text()) if args.out.exists() else {}
    with bench_common.report(__file__, args.out, statistic="median", repeats=args.repeats,
                             settings=before.get("settings", {})) as record:
        run_all(args, record)


def run_all(args, record: bench_common.Report) -> None:
    seeds = 1 if args.quick else args.seeds
    for setting in args.settings:
        entry = record["settings"].setdefault(setting, {"runs": {}})
        epochs = max(2, EPOCHS[setting] // 5) if args.quick else EPOCHS[setting]
        modes = ("converged", "prdp", "prdp-strict") if setting in args.strict else ("converged", "prdp")
        for seed in range(seeds):
            for mode in modes:                          # one after the other: the same machine load
                key = f"{mode}-{seed}"
                if key in entry["runs"] and entry["runs"][key].get("epochs") == epochs \
                        and entry["runs"][key].get("validation") == VALIDATION:
                    continue
                one_run = functools.partial(train_ddp, mode, seed, epochs) if setting == "ddp" \
                    else functools.partial(train, setting, mode, seed, epochs)
                run = bench_common.repeat_runs(one_run, "wall_time", statistic="median",
                                               repeats=args.repeats if setting in REPEATED else 1)
                run["wall_times"] = run.pop("wall_time_samples")
                entry["runs"][key] = {**run, "epochs": epochs, "validation": VALIDATION}
                entry["summary"] = summarise(entry["runs"])
                record.sample_load(f"{setting} {key}")
                record.save()
                print(f"{setting:15s} {key:12s} metric {run['final_metric']:.3e} wall {run['wall_time']:7.1f} s "
                      f"newton {run['newton_steps']:7d} inner {run['inner_iterations']:9d} K {run['k0']}.."
                      f"{run['k_schedule'][-1]} (K_eps {run['k_eps']})", flush=True)
        print(setting, json.dumps({key: value for key, value in entry.get("summary", {}).items()
                                   if key.endswith("_over_converged")}), flush=True)


if __name__ == "__main__":
    main()
