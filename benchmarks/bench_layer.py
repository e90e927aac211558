"""Benchmark: what SolveLayer costs over hand-written PETSc, and what batching saves.

Setup: Poisson's equation -div(grad u) = f on the bundled L-shape, meshed at
two sizes (``small`` h=0.03, about 4k P1 DOFs; ``large`` h=0.0073, about 66k),
with u = g on the whole boundary and the source f as the only control
(``fempdl.forms.poisson.problem(msh, controls=("f",), g=...)``). The solver is
capped at K iterations: Richardson + Jacobi (``KSPOptions(max_it=K)``) and
GMRES(30) + Jacobi (``KSPOptions.preset("gmres", max_it=K)``). Each sample of
a batch of B random sources is solved, and the loss sum(u * W) is
backpropagated to the sources.

Measured per (size, solver, K):

(a) layer overhead = time of ``u = layer(f=F); (u * W).sum().backward()`` for
    F of shape (B, n), with ``engine="petsc"`` (one KSP solve per sample, the
    same work as the raw loop), divided by the time of a raw petsc4py loop doing the same
    work by hand (b_i = M f_i + b0, a KSP solve with the same options, copy
    out; then per sample A^T lam_i = w_i and M^T lam_i). The raw loop's
    matrices, Dirichlet condition and KSP are built with dolfinx/petsc4py
    directly, not through fempdl (``layer_raw_loop.py``), and its solutions and gradients are compared
    with the layer's: the max relative difference is recorded (0 or round-off:
    both run the same floating-point operations), beside the change one more
    iteration makes, to show the comparison would catch a different solve.
    Target: ratio <= 1.15.
(b) batching speed-up = time of B separate layer calls with (1, n) tensors
    divided by the time of one call with the (B, n) tensor (forward and
    backward, the same total work), both with the default ``engine="auto"``,
    which runs a batch of Jacobi solves on the batched engine
    (:mod:`fempdl.iterative.batched`) and single samples through PETSc. Target: >= 1.5.
    Also reported: engine speed-up = the ``engine="petsc"`` batched call over
    the ``engine="auto"`` one.

Also recorded: DOFs, K, B, absolute times in seconds, the layer's forward and
backward iteration counts for one batched call, a breakdown of the batched
call (KSP time, other time inside the layer, time outside it: torch and
autograd), the raw loop's KSP time, the layer's fixed cost per call, the
machine and its load average.

Timing: every configuration is warmed up once (form JIT compilation, KSP
setup) before it is timed; the four timed variants (batched calls with both engines, raw
loop, B single calls) are interleaved within each repeat so that load from
other processes affects them alike (``bench_common.interleaved``). Each runs ``--repeats`` times, and cheap
configurations more often (up to 100 times, until the batched calls add up
to ``--min-time`` seconds). The reported time of each variant is the
**minimum** over its repeats: other processes only ever add time, so the
minimum is the least disturbed estimate (every repeat is in the JSON).
torch keeps its own thread count (``--threads`` to set it; recorded): the
batched engine's sparse products use those threads, PETSc runs on one.
Runs serially (one MPI rank).

Run (from the repository root)::

    .venv/bin/python benchmarks/bench_layer.py                 # full: both sizes, K=10,50,200, B=32, 3 repeats
    .venv/bin/python benchmarks/bench_layer.py --quick         # smoke test: small mesh, K=10,50, B=8, 1 repeat
    .venv/bin/python benchmarks/bench_layer.py --sizes small --ks 10 --solvers jacobi --out /tmp/b.json

Figures go to ``bench-results/bench_layer.json`` (``--out`` to change); a
short table is printed.
"""
from __future__ import annotations

import argparse
import sys
import time

from mpi4py import MPI  # before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads
import numpy as np
import torch
from layer_raw_loop import SOLVERS, RawLoop, boundary_values

import fempdl.core.mesh
import fempdl.forms
from fempdl.bridge_torch import SolveLayer

import bench_common
from bench_common import apply_defaults, comma_list, interleaved, pick

MESH_SIZES = {"small": 0.03, "large": 0.0073}   # h -> about 4k and 66k P1 DOFs (fempdl.core.meshgen)
TARGET_OVERHEAD = 1.15
TARGET_BATCH_SPEEDUP = 1.5
STATISTIC = "min"
MAX_REPEATS = 100


# ---------------------------------------------------------------- timed work
def layer_call(layer: SolveLayer, F: torch.Tensor, W: torch.Tensor) -> torch.Tensor:
    F.grad = None
    u = layer(f=F)
    (u * W).sum().backward()
    return u


def time_layer_call(layer, F, W) -> dict:
    """Wall time of one batched call, split into KSP, rest of the layer, and torch/autograd."""
    stats = layer.stats
    ksp0, inside0 = stats.solve_time, stats.layer_time
    t0 = time.perf_counter()
    layer_call(layer, F, W)
    wall = time.perf_counter() - t0
    ksp, inside = stats.solve_time - ksp0, stats.layer_time - inside0
    return {"wall": wall, "ksp": ksp, "layer_other": inside - ksp, "outside_layer": wall - inside}


def time_raw_loop(raw: RawLoop, F: np.ndarray, W: np.ndarray) -> dict:
    raw.ksp_time = 0.0
    t0 = time.perf_counter()
    raw.forward(F)
    raw.backward(W)
    wall = time.perf_counter() - t0
    return {"wall": wall, "ksp": raw.ksp_time}


def time_per_sample_calls(layer, rows: list, W_rows: list) -> float:
    t0 = time.perf_counter()
    for f, w in zip(rows, W_rows):
        layer_call(layer, f, w)
    return time.perf_counter() - t0


def recorded(runs: list, fn, *args):
    """A measurement for ``interleaved``: ``fn(*args)``'s record appended to ``runs``, its wall time returned."""
    def run() -> float:
        runs.append(fn(*args))
        return runs[-1]["wall"]
    return run


# --------------------------------------------------------------- correctness
def max_relative_difference(X: np.ndarray, Y: np.ndarray) -> float:
    """max over samples of ||x_i - y_i|| / ||y_i||."""
    return float(np.max(np.linalg.norm(X - Y, axis=1) / np.linalg.norm(Y, axis=1)))


def check_against_raw(layer, raw: RawLoop, F, W, max_it: int) -> tuple[dict, dict]:
    """Compare layer and raw loop, and count the layer's iterations (this is also
    the warm-up of both)."""
    layer.stats.reset()
    u = layer_call(layer, F, W).detach().numpy()
    iterations = {"forward": layer.stats.forward_iterations, "backward": layer.stats.backward_iterations}
    U_raw = raw.forward(F.detach().numpy())
    grads_raw = raw.backward(W.numpy())
    # What one more iteration changes: the scale the differences above must be far below.
    raw.set_max_it(max_it + 1)
    U_more = raw.forward(F.detach().numpy()[:1])
    raw.set_max_it(max_it)
    check = {
        "max_rel_diff_u": max_relative_difference(u, U_raw),
        "max_rel_diff_grad": max_relative_difference(F.grad.numpy(), grads_raw),
        "rel_change_one_more_iteration": max_relative_difference(U_more, U_raw[:1]),
    }
    return check, iterations


# --------------------------------------------------------------- one config
def bench_config(layers: dict, raw: RawLoop, F, W, max_it: int, repeats: int, min_time: float) -> dict:
    """Time the variants, interleaved, ``repeats`` times, and more often (up to
    MAX_REPEATS) while the batched calls have run for less than ``min_time`` s.

    ``layers["petsc"]`` runs every sample through a KSP (the layer-overhead
    comparison with the raw loop); ``layers["auto"]`` is the default engine
    choice (the batched engine for Jacobi), used for the batching speed-up.
    """
    for layer in layers.values():
        layer.max_it = max_it
    raw.set_max_it(max_it)
    check, iterations = check_against_raw(layers["petsc"], raw, F, W, max_it)
    check_auto, _ = check_against_raw(layers["auto"], raw, F, W, max_it)
    check["auto_engine"] = check_auto
    engine = layers["auto"].stats.last.engine
    rows = [F[i:i + 1].detach().clone().requires_grad_() for i in range(F.shape[0])]
    W_rows = [W[i:i + 1] for i in range(W.shape[0])]
    F_np, W_np = F.detach().numpy(), W.numpy()
    petsc, auto, reference = [], [], []
    timings = interleaved({"auto": recorded(auto, time_layer_call, layers["auto"], F, W),
                           "petsc": recorded(petsc, time_layer_call, layers["petsc"], F, W),
                           "raw": recorded(reference, time_raw_loop, raw, F_np, W_np),
                           "per_sample": lambda: time_per_sample_calls(layers["auto"], rows, W_rows)},
                          repeats=repeats, warmup=0, statistic=STATISTIC, min_time=min_time,
                          min_time_of="auto", max_repeats=MAX_REPEATS)
    per_sample = list(timings["per_sample"].samples)
    fastest, fastest_auto, fastest_raw = (pick(runs, "wall", STATISTIC) for runs in (petsc, auto, reference))
    layer_s, auto_s = fastest["wall"], fastest_auto["wall"]
    raw_s, per_sample_s = fastest_raw["wall"], timings["per_sample"].seconds
    return {
        "K": max_it,
        "B": F.shape[0],
        "repeats": len(petsc),
        "engine_auto": engine,
        "times_s": {
            "layer_petsc_engine": layer_s,
            "layer_auto_engine": auto_s,
            "raw_loop": raw_s,
            "layer_per_sample_loop": per_sample_s,
            "all_repeats": {
                "layer_petsc_engine": [t["wall"] for t in petsc],
                "layer_auto_engine": [t["wall"] for t in auto],
                "raw_loop": [t["wall"] for t in reference],
                "layer_per_sample_loop": per_sample,
            },
        },
        # Of the fastest repeat of each.
        "breakdown_s": {
            "layer_petsc_engine": {k: fastest[k] for k in ("ksp", "layer_other", "outside_layer")},
            "layer_auto_engine": {k: fastest_auto[k] for k in ("ksp", "layer_other", "outside_layer")},
            "raw_loop": {"ksp": fastest_raw["ksp"], "other": raw_s - fastest_raw["ksp"]},
        },
        "ratios": {
            "layer_overhead": layer_s / raw_s,
            "batching_speedup": per_sample_s / auto_s,
            "engine_speedup": layer_s / auto_s,
        },
        # B single calls do the batched call's work plus B - 1 calls' fixed costs.
        "per_call_fixed_cost_s": (per_sample_s - layer_s) / (F.shape[0] - 1),
        "targets_met": {
            "layer_overhead": layer_s / raw_s <= TARGET_OVERHEAD,
            "batching_speedup": per_sample_s / auto_s >= TARGET_BATCH_SPEEDUP,
        },
        "iterations_per_batched_call": iterations,
        "check": check,
    }


def bench_size(size: str, args: argparse.Namespace, rng) -> tuple[dict, list]:
    h = MESH_SIZES[size]
    msh = fempdl.core.mesh.load("lshape", h=h)
    prob = fempdl.forms.poisson.problem(msh, controls=("f",), g=boundary_values)
    n = prob.control_size("f")
    mesh_info = {"h": h, "dofs": prob.output_size,
                 "cells": msh.mesh.topology.index_map(msh.tdim).size_local}
    F = torch.from_numpy(rng.standard_normal((args.batch, n))).requires_grad_()
    W = torch.from_numpy(rng.standard_normal((args.batch, prob.output_size)))
    results = []
    for name in args.solvers:
        solver = SOLVERS[name]
        layers = {engine: SolveLayer(prob, solver.layer_options(args.ks[0], engine))
                  for engine in ("petsc", "auto")}
        raw = RawLoop(prob.V, solver, args.ks[0])
        for k in args.ks:
            row = bench_config(layers, raw, F, W, k, args.repeats, args.min_time)
            row.update(size=size, dofs=prob.output_size, solver=name)
            results.append(row)
            print_row(row, flush=True)
        for layer in layers.values():
            layer.close()
        raw.destroy()
    return mesh_info, results


# ------------------------------------------------------------------- output
HEADER = (f"{'size':<6}{'dofs':>7} {'solver':<7}{'K':>4}{'B':>4} {'layer s':>9}{'raw s':>9}"
          f"{'overhead':>9} {'engine':>8}{'auto s':>9}{'1-by-1 s':>9}{'speedup':>8} {'its f+b':>8} "
          f"{'rel diff u':>11}{'reps':>5}")


def print_row(row: dict, flush: bool = False) -> None:
    t, r = row["times_s"], row["ratios"]
    its = row["iterations_per_batched_call"]
    diff = max(row["check"]["max_rel_diff_u"], row["check"]["auto_engine"]["max_rel_diff_u"])
    print(f"{row['size']:<6}{row['dofs']:>7} {row['solver']:<7}{row['K']:>4}{row['B']:>4} "
          f"{t['layer_petsc_engine']:>9.4f}{t['raw_loop']:>9.4f}{r['layer_overhead']:>9.3f} "
          f"{row['engine_auto']:>8}{t['layer_auto_engine']:>9.4f}"
          f"{t['layer_per_sample_loop']:>9.4f}{r['batching_speedup']:>8.3f} "
          f"{its['forward'] + its['backward']:>8} {diff:>11.1e}{row['repeats']:>5}",
          flush=flush)


# ---------------------------------------------------------------------- CLI
def parse_args(argv=None) -> argparse.Namespace:
    parser = bench_common.parser(__file__, __doc__.split("\n\n")[0], repeats=3, quick_repeats=1,
                                 quick="small mesh, K=10,50, B=8 (explicit flags still win)")
    parser.add_argument("--sizes", type=comma_list(str), help="mesh sizes: small,large (default both)")
    parser.add_argument("--ks", type=comma_list(int), help="iteration caps K (default 10,50,200)")
    parser.add_argument("--batch", type=int, help="batch size B (default 32)")
    parser.add_argument("--min-time", type=float,
                        help="repeat cheap configurations until the batched calls add up to this "
                             "many seconds (default 1.0; 0 with --quick)")
    parser.add_argument("--solvers", type=comma_list(str),
                        help="jacobi (Richardson+Jacobi) and/or gmres (GMRES(30)+Jacobi); default both")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random sources and weights")
    parser.add_argument("--threads", type=int,
                        help="torch threads (default: torch's own choice; the batched engine uses them, "
                             "PETSc runs on one)")
    args = parser.parse_args(argv)
    defaults = ({"sizes": ["small"], "ks": [10, 50], "batch": 8, "min_time": 0.0,
                 "solvers": ["jacobi", "gmres"]} if args.quick
                else {"sizes": ["small", "large"], "ks": [10, 50, 200], "batch": 32,
                      "min_time": 1.0, "solvers": ["jacobi", "gmres"]})
    apply_defaults(parser, args, defaults, MESH_SIZES, SOLVERS)
    if args.batch < 2 or args.min_time < 0:
        parser.error("--batch must be >= 2 (batching is compared with B single calls) and --min-time >= 0")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if MPI.COMM_WORLD.size > 1:
        print("bench_layer.py compares against a serial PETSc loop; run it without mpirun", file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    rng = np.random.default_rng(args.seed)
    started = time.perf_counter()
    settings = {"sizes": args.sizes, "ks": args.ks, "batch": args.batch, "min_time_s": args.min_time,
                "max_repeats": MAX_REPEATS, "solvers": args.solvers, "seed": args.seed,
                "problem": "poisson on lshape, control f, g = 1 + x*y on the whole boundary",
                "loss": "sum(u * W), W standard normal"}
    with bench_common.report(__file__, args.out, statistic=STATISTIC, repeats=args.repeats, settings=settings,
                             targets={"layer_overhead_max": TARGET_OVERHEAD,
                                      "batching_speedup_min": TARGET_BATCH_SPEEDUP},
                             meshes={}, results=[]) as report:
        print(HEADER)
        for size in args.sizes:
            mesh_info, rows = bench_size(size, args, rng)
            report["meshes"][size] = mesh_info
            report["results"].extend(rows)
        report["duration_s"] = time.perf_counter() - started
    print(f"overhead = layer (engine='petsc') / raw loop (target <= {TARGET_OVERHEAD}); engine, auto s = "
          f"the default engine's choice and its batched call; speedup = B single calls / that batched call "
          f"(target >= {TARGET_BATCH_SPEEDUP}); times are the {STATISTIC} over repeats (column 'reps'); "
          f"torch threads {torch.get_num_threads()}; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
