"""Benchmark: PRDP against converged solves in training loops written as users write them.

Each setting is a hand-written loop (no scene, no CLI), trained per seed with the same data, network
initialisation and batches:

* ``converged``: the cap at K_eps, what converged solves of the loop's validation inputs need from zero
  (:func:`fempdl.prdp.k_eps`, or ``newton_k_eps``, to their default tolerance 1e-8); a Newton solve stops
  at its tolerance before it;
* ``prdp``: the README's way: ``PRDP(caps, k0=k_start(...), k_cap=k_eps(...))`` with every other setting
  PRDP's default (growth 1.5, the gap at every step, the health check of forward and adjoint solves);
* ``defaults``: PRDP built only from ``preflight``'s printed advice, as a new user who takes it literally
  does: ``report = preflight(train_step, caps, **inputs)``, ``PRDP(caps, **report.advice())`` (the
  ``PRDP(target, k0=..., k_cap=...)`` its summary prints), no other setting; its wall time includes
  preflight (whose training steps are undone, so every mode starts from one state);
* ``prdp-strict`` (``--strict``): ``prdp`` with k0 within 1% of converged solves.

Every PRDP run steps on the validation as a function, ``ctrl.step(loop.metric)``, which PRDP runs at
reference physics (LU; a converged Newton) and at the caps, and ends with ``ctrl.finish(loop.metric)``;
the converged loop runs the same validation at reference physics. The wall time includes them.

Settings:

* ``readme-as-written``: the README's loop itself (the bundled L-shape, 1.5k DOFs, 64 samples in one
  batch, 200 epochs); ``readme``: a shorter one on a coarser mesh;
* ``warm-linear``: a heat-step emulator (a residual network advances u0 -> u1, a capped heat step u1 -> u2
  warm-started from u1, the loss against two converged steps); ``hole-emulator``: the same on the bundled
  obstacle channel (h = 0.03); ``ddp``: ``warm-linear`` under torchrun on 2 processes (gloo);
* ``plate-40`` / ``plate-200``: a new user's emulator on a gmsh plate with a hole that the benchmark
  meshes itself (an MLP gives u0 from 9 mode amplitudes, a Jacobi heat step from zero advances it), 40 and
  200 epochs;
* ``newton-cold`` / ``newton-warm``: an inverse problem through Newton solves (a coordinate MLP gives kappa
  in a regularised p-Laplacian, 4 sources, 40 sensors, LU inner solves), from zero or from the previous
  step's states (the metric is the training loss: such a loop has no validation set);
* ``nonlinear-heat``: the emulator through one backward-Euler step of -div((1 + 20 u^2) grad u);
* ``newton-rollout``: an MLP source in 20 implicit nonlinear heat steps fitted to 30 sensors at 4 times;
* ``stokes-inverse``: a body force of 3 coefficients fitted to the velocity at 300 DOFs (1% noise) of a
  Stokes flow on the obstacle channel, Schur-complement GMRES capped at K, its gradient the implicit one.

The loops themselves are in ``prdp_loops_cases.py``; this script trains them and records the runs.

Recorded per run: the metric at the end evaluated with converged solves, Newton steps and inner
iterations (forward + backward, training and validation, all ranks), the training wall time, the K
schedule, refinements and their causes, preflight's summary and ``finish``'s record; per setting the means
over the seeds and the ratios over converged, and the targets (mean metric <= 1.05x, no seed above 1.15x,
wall time <= 1.00x). The loops of a few seconds run ``--repeats`` (5) times (the same numbers but the wall
time, whose median is kept, ``bench_common.repeat_runs``). Writes ``bench-results/bench_prdp_loops.json``
(``--out``, through ``bench_common.report``, with the load after every run) after every run and resumes
from it. Run on an idle machine: ``python benchmarks/bench_prdp_loops.py``; ``--quick`` runs one seed of
shortened loops.
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
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
from fempdl.prdp import k_eps, k_start, newton_k_eps, preflight, reference_physics

import bench_common
from bench_common import comma_list

SETTINGS = ("readme-as-written", "readme", "warm-linear", "hole-emulator", "newton-cold", "newton-warm",
            "nonlinear-heat", "newton-rollout", "ddp", "plate-40", "plate-200", "stokes-inverse")
# Settings that also train with PRDP built only from preflight's printed advice ("defaults").
DEFAULTS = ("plate-40", "plate-200", "readme-as-written", "newton-cold", "stokes-inverse", "newton-rollout",
            "warm-linear", "hole-emulator", "ddp")
STRICT = ()
REPEATED = ("warm-linear", "ddp")         # loops of a few seconds: run --repeats times
K0_TOLERANCE = {"prdp": None, "prdp-strict": 0.01}    # None: k_start's default (by what the capped gradient is)
PRDP_MODES = ("prdp", "prdp-strict", "defaults")
EPOCHS = {"readme-as-written": 200, "hole-emulator": 60, "newton-rollout": 80, "readme": 60, "warm-linear": 60,
          "newton-cold": 300, "newton-warm": 300, "nonlinear-heat": 40, "ddp": 60, "plate-40": 40, "plate-200": 200,
          "stokes-inverse": 150}
# How the runs validate: at reference physics, the gap measured at every step (PRDP steps on a function it runs
# converged and capped; the converged loop runs the same validation at reference physics). Runs recorded
# before ("capped", or "reference" with the gap measured on plateaus only) are run again.
VALIDATION = "reference, gap every step"
# The README's rule: PRDP's defaults (growth 1.5: as many refinements from k0 to K_eps whether K_eps is 10 or
# 500 iterations; the gap at every step).
PRDP_RULE: dict = {}


def caps_for(loop, tolerance: float | None) -> tuple[int, int]:
    """(K0, K_eps) as the README measures them: K_eps from zero on the loop's validation inputs (to
    k_eps' default tolerance, 1e-8), k0 from the starts the loop uses (k_start's default tolerance for None);
    a rollout's both on its own calls at the initial model."""
    if hasattr(loop, "probe"):
        keps = k_eps(loop.caps, call=loop.probe)
        return min(k_start(loop.caps, tolerance=tolerance, k_max=keps, call=loop.probe), keps), keps
    cold = {k: v for k, v in loop.inputs.items() if k != "initial_guess"}
    keps = newton_k_eps(loop.caps, **cold) if isinstance(loop.caps, NewtonCaps) else k_eps(loop.caps, **cold)
    return min(k_start(loop.caps, tolerance=tolerance, k_max=keps, **loop.inputs), keps), keps


def preflight_inputs(loop) -> dict:
    """What the loop's own validation passes its target: ``preflight``'s keyword inputs, or its ``call=``."""
    return {"call": loop.probe} if hasattr(loop, "probe") else dict(loop.inputs)


def training_state(loop) -> dict:
    """What a training step changes in a loop: its network or parameters, optimiser, schedule, batch order
    and warm start, copied."""
    kept = {name: copy.deepcopy(getattr(loop, name).state_dict()) for name in ("net", "opt", "decay")
            if hasattr(loop, name)}
    kept.update({name: copy.deepcopy(getattr(loop, name)) for name in ("state", "loss") if hasattr(loop, name)})
    if hasattr(loop, "theta"):
        kept["theta"] = loop.theta.detach().clone()
    if hasattr(loop, "order"):
        kept["order"] = loop.order.get_state()
    return kept


def restore_training_state(loop, kept: dict) -> None:
    for name, value in kept.items():
        if name in ("net", "opt", "decay"):
            getattr(loop, name).load_state_dict(value)
        elif name == "theta":
            with torch.no_grad():
                loop.theta.copy_(value)
        elif name == "order":
            loop.order.set_state(value)
        else:
            setattr(loop, name, value)


def train(setting: str, mode: str, seed: int, epochs: int, rank: int = 0, size: int = 1) -> dict:
    loop = build(setting, seed, rank, size)
    t0 = time.perf_counter()
    advice = None
    if mode == "defaults":                          # a user who takes preflight's printed advice literally
        kept = training_state(loop)                 # preflight's steps train; every mode starts from one state
        report = preflight(loop.train_step, loop.caps, **preflight_inputs(loop))
        restore_training_state(loop, kept)
        advice = report.summary()
        ctrl = PRDP(loop.caps, **report.advice())   # the PRDP(target, k0=..., k_cap=...) the summary prints
        k0, keps = report.k0, report.k_cap
    else:
        k0, keps = caps_for(loop, K0_TOLERANCE.get(mode))
        t0 = time.perf_counter()                    # the caps of the chosen rule are not timed
        ctrl = PRDP(loop.caps, k0=k0, k_cap=keps, **PRDP_RULE) if mode != "converged" else None
    preflight_time = time.perf_counter() - t0
    if ctrl is None:
        loop.caps.max_it = keps
    ks = []
    for _ in range(epochs):
        loop.epoch()
        ks.append(loop.caps.max_it)
        if ctrl is not None:
            ctrl.step(loop.metric)                  # at reference physics and at the caps: the gap rule
        else:
            with torch.no_grad(), reference_physics(loop.layers):
                loop.metric()                       # the same validation, at the same cost
    finish = None if ctrl is None else dataclasses.asdict(ctrl.finish(loop.metric))
    wall = time.perf_counter() - t0
    counts = torch.tensor([float(sum(getattr(s, name, 0) for s in (layer.stats for layer in loop.layers)))
                           for name in ("newton_steps", "backward_newton_steps", "forward_iterations",
                                        "backward_iterations")], dtype=torch.float64)
    counts = all_reduce(counts)
    reference = [layer.reference_stats for layer in loop.layers if layer.reference_stats is not None]
    return {"mode": mode, "seed": seed, "k0": k0, "k_eps": keps, "k_schedule": ks, "wall_time": wall,
            "preflight_time": preflight_time, "advice": advice, "finish": finish,
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
    by_mode = {mode: [r for r in runs.values() if r["mode"] == mode] for mode in ("converged", *PRDP_MODES)}
    by_mode = {mode: rs for mode, rs in by_mode.items() if rs}
    if "converged" not in by_mode or "prdp" not in by_mode:
        return {}
    mean = {mode: {key: statistics.fmean(r[key] for r in rs) for key in
                   ("final_metric", "wall_time", "newton_steps", "inner_iterations")}
            for mode, rs in by_mode.items()}
    base = mean["converged"]
    summary = {"mean": mean}
    for mode in PRDP_MODES:
        if mode in mean:
            ratio = {key: (mean[mode][key] / base[key] if base[key] else None) for key in base}
            summary[f"{mode}_over_converged"] = ratio
            worst = max(r["final_metric"] / base["final_metric"] for r in by_mode[mode])
            summary.setdefault("targets", {})[mode] = {"metric_within_1.05": ratio["final_metric"] <= 1.05,
                                                       "no_seed_above_1.15": worst <= 1.15,
                                                       "wall_at_most_1.00": ratio["wall_time"] <= 1.0}
    return summary


def main() -> None:
    parser = bench_common.parser(__file__, __doc__.split("\n\n")[0], repeats=5, quick_repeats=1,
                                 quick="one seed, a fifth of the epochs")
    parser.add_argument("--settings", type=comma_list(str), default=list(SETTINGS))
    parser.add_argument("--seeds", type=int, default=3)
    parser.add_argument("--strict", type=comma_list(str), default=list(STRICT),
                        help="settings also run with k0 within 1%% of converged solves")
    parser.add_argument("--modes", type=comma_list(str), default=["converged", *PRDP_MODES],
                        help="the modes to train (converged, prdp, prdp-strict, defaults)")
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
        modes = ("converged", "prdp") + ("prdp-strict",) * (setting in args.strict) \
            + ("defaults",) * (setting in DEFAULTS)
        modes = tuple(mode for mode in modes if mode in args.modes)
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
