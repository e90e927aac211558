"""Benchmark: unrolled vs implicit differentiation of a capped solve (time, memory), and the batched engine.

Setup: Poisson's equation -div(grad u) = f on the bundled L-shape, meshed at
two sizes (``small`` h=0.03, about 4k P1 DOFs; ``large`` h=0.0073, about 66k),
u = 0 on the whole boundary, the source f the only control
(``fempdl.forms.poisson.problem(fempdl.core.mesh.load("lshape", h=h), controls=("f",))``).
Solvers capped at K iterations: Richardson + Jacobi (``KSPOptions(max_it=K)``)
and CG + Jacobi (``KSPOptions.preset("cg", max_it=K)``). A batch of B random
sources F (B, n) is solved and the loss sum(u * W) backpropagated to F:
``u = layer(f=F); (u * W).sum().backward()``. That call, forward plus
backward, is what every variant below times.

Measured per (size, solver, K):

(1) ``diff="unrolled"`` (autograd through the K iterations in torch,
    :mod:`fempdl.iterative.unrolled`) against ``diff="implicit"`` (one capped adjoint
    solve), both with the default ``engine="auto"``: wall time and peak
    memory, and their ratios unrolled / implicit. Peak memory is the increase
    of the process's peak resident set size (RSS) during the call, measured
    in a fresh subprocess per measurement (this script with a hidden
    ``--child`` option), so that no other configuration's allocations or
    allocator caches are in it. The child reads the same mesh from a
    ``.msh`` file written once per size (``fempdl.core.meshgen.write_msh``; reading
    takes 0.8 s where meshing the 66k DOF size takes 5 s), builds the
    problem and the layer, warms up on two samples (form JIT, assembly, the
    torch copies of the operators, the code paths of the batched call; a
    sixteenth of the batch's memory), resets the kernel's peak-RSS mark
    (``/proc/self/clear_refs``, value 5), runs the call and reports the peak mark after it (``VmHWM``;
    ``getrusage(RUSAGE_SELF).ru_maxrss`` is recorded too, but it can keep a
    peak from before the reset once a thread has exited) minus the RSS
    before it, in MiB. Without the reset (no /proc) the increase of ru_maxrss
    is reported, an underestimate (``peak_reset: false``). RSS counts
    everything the call allocates (torch tensors, NumPy arrays, PETSc
    vectors, memory the allocator keeps after a free), which torch's own
    allocation tracking or tracemalloc would each see only in part.
    For comparison: the theoretical size of the stored iterates,
    ``fempdl.iterative.unrolled.stored_values(method, K, n, B) * 8`` bytes. A
    configuration is skipped (``skipped`` in the JSON) when 2.5 times that
    does not fit in the memory available: the largest, CG with K=100 on 66k
    DOFs at B=32, stores 7.8 GiB and took 14.7 GiB (the full run needs a
    machine with about 20 GiB free).
(2) the batched engine against the per-sample PETSc loop, implicit mode, same
    K: ``engine="batched"`` (one sparse-times-dense product per iteration for
    the whole batch) against ``engine="petsc"`` (one KSP solve per sample);
    the ratio petsc / batched is the engine's speed-up.
(3) at the largest K: unrolled with checkpointing, ``max_unrolled_values`` set
    to the least a checkpointed solve keeps (``unrolled.checkpointed_values``;
    the iterations then run in segments of about sqrt(K), recomputed in
    backward): its time and memory over plain unrolled. Not for Jacobi, whose unrolled solve keeps no
    per-iteration state (``stored_values`` is 0).

Checks (on the warm-up calls; max over samples of ||a_i - b_i|| / ||b_i||,
all recorded): the forward outputs of unrolled and implicit (default engine)
must agree to 1e-12, and so must checkpointed and plain unrolled, forward and
gradient. Capped CG amplifies round-off with K (the two modes form the
right-hand side M f + b0 in torch and in PETSc, which differ in the last
bit): the forward tolerance is therefore max(1e-12, 10 x the change of the
output when F is perturbed by a relative 1e-15 at random), the sensitivity
being recorded beside it; for Jacobi it stays 1e-12. For Jacobi the
gradients of unrolled and implicit must agree to 1e-12 too
(Richardson+Jacobi's implicit gradient is the exact VJP of the K-step map),
and so must both against the PETSc engine, an independent implementation.
For CG the relative gradient difference is only recorded (the implicit
gradient of capped CG is not the VJP of the capped map, by design: it
approaches it as K grows), and so is the difference to PETSc's KSPCG.

Timing: every variant is warmed up once (form JIT, assembly, KSP setup,
operator copies) before it is timed; within each repeat the variants run
interleaved (``bench_common.interleaved``), so that load from other processes affects them alike. Each runs
``--repeats`` times, and cheap configurations more often (up to 20 times,
until the repeats of all variants together have taken ``--min-time`` s).
Configurations whose unrolled call stores more than ``--heavy-gib`` GiB of
iterates (the 66k DOF, K=100 ones) run ``--heavy-repeats`` times instead
(recorded per row as ``repeats`` and ``heavy``, and in the settings). The reported time of each
variant is the **minimum** over its repeats: other processes only ever add
time (every repeat is in the JSON). Memory does not depend on load, but the
same call's peak RSS varies from process to process (for unrolled CG on the
4k mesh it fell in one of two modes, 380 or 850-920 MiB, with nothing
changed: where the allocator places and returns freed blocks differs): it is
measured in ``--memory-repeats`` fresh processes per variant (heavy
configurations: at most ``--heavy-repeats``), and the minimum is reported,
with every sample. Serial only (unrolled mode is serial).

Threads: torch keeps its own thread count (``--threads`` to set it;
recorded): the batched engine and the unrolled iterations use those threads,
PETSc runs on one. The OpenMP wait policy is set to passive
(``OMP_WAIT_POLICY=PASSIVE``, unless the environment sets it;
``--omp-wait-policy=default`` keeps the runtime's spin-then-sleep default):
on this 2-core machine with another process busy on one core, torch's two
OpenMP threads under the default policy stalled at every parallel region,
making a batched or unrolled call 10-80 times slower, at random (a CG call of
0.3 s took 12-25 s; the minimum over repeats did not remove it), while with
the passive policy the same calls ran at their unloaded speed, which costs a
few microseconds per parallel region at most. The policy in force is recorded.

Run (from the repository root)::

    .venv/bin/python benchmarks/bench_unrolled.py            # full: both sizes, K=5,20,100, B=32 (9.5 min idle)
    .venv/bin/python benchmarks/bench_unrolled.py --quick    # smoke test: small mesh, K=5,20, B=8, no memory
    .venv/bin/python benchmarks/bench_unrolled.py --sizes small --ks 20 --solvers cg --out /tmp/u.json

Figures go to ``bench-results/bench_unrolled.json`` (``--out`` to change); a
table is printed. The workload and its checks are in ``unrolled_cases.py``, the memory
subprocesses in ``unrolled_memory.py``, the table in ``unrolled_table.py``.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import sys
import tempfile
import time
from pathlib import Path

# OpenMP reads its wait policy when the runtime loads (with torch, below), so this comes first;
# see "Threads" in the docstring. Children inherit the environment.
OMP_POLICY_OPTION = "--omp-wait-policy"


def _omp_policy_arg(argv: list) -> str:
    """The value of --omp-wait-policy (as --opt=VALUE or --opt VALUE), before argparse runs."""
    for i, arg in enumerate(argv):
        if arg.startswith(OMP_POLICY_OPTION + "="):
            return arg.split("=", 1)[1]
        if arg == OMP_POLICY_OPTION and i + 1 < len(argv):
            return argv[i + 1]
    return "passive"


_OMP_POLICY_ARG = _omp_policy_arg(sys.argv[1:])
if _OMP_POLICY_ARG == "passive":
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from mpi4py import MPI  # noqa: E402
import torch  # noqa: E402
from unrolled_cases import (  # noqa: E402
    AGREEMENT_TOL,
    MESH_SIZES,
    SOLVERS,
    VARIANTS,
    build_problem,
    check_outputs,
    checkpoint_limit,
    layer_call,
    make_inputs,
    make_layer,
    round_off_sensitivity,
    stored_bytes,
)
from unrolled_memory import child_main, measure_memory_repeated, release_free_memory  # noqa: E402
from unrolled_table import HEADER, print_row  # noqa: E402

import fempdl.core.meshgen  # noqa: E402
from fempdl.core.resources import available_memory  # noqa: E402

import bench_common  # noqa: E402
from bench_common import apply_defaults, comma_list, interleaved, pick  # noqa: E402

STATISTIC = "min"
MAX_REPEATS = 20
MEMORY_VARIANTS = ("implicit", "unrolled", "unrolled_checkpointed")
MIB = 2.0 ** 20
# Peak RSS increase of an unrolled call over its stored_values * 8 bytes: measured 0.6-1.05 for
# Jacobi and up to 1.9 for CG (K=100, both meshes); a configuration is skipped when this bound
# times the stored size does not fit in MemAvailable.
UNROLLED_MEMORY_BOUND = 2.5


def bench_config(layers: dict, size: str, solver: str, K: int, F, W, args, heavy: bool,
                 largest_k: bool) -> dict:
    n, batch = F.shape[1], F.shape[0]
    limit = checkpoint_limit(solver, K, n, batch)
    # Checkpointing needs something to bound: Jacobi keeps no per-iteration state.
    names = [v for v in VARIANTS if (largest_k and limit > 0) or v != "unrolled_checkpointed"]
    for v in names:
        layers[v].max_it = K
    layers["unrolled_checkpointed"].max_unrolled_values = limit
    # Warm-up, also the correctness check and the engine each variant ran on.
    warm = {}
    engines = {}
    for v in names:
        layers[v].stats.reset()
        warm[v] = layer_call(layers[v], F, W)
        engines[v] = dict(layers[v].stats.solves_by_engine)
    check = check_outputs(warm, solver, round_off_sensitivity(layers["implicit"], F, warm["implicit"]["u"]))
    del warm
    gc.collect()

    repeats = args.heavy_repeats if heavy else args.repeats
    runs = {v: [] for v in names}

    def variant(v: str):
        def run() -> float:
            call = layer_call(layers[v], F, W)
            runs[v].append({k: call[k] for k in ("forward", "backward", "wall")})
            return runs[v][-1]["wall"]
        return run

    interleaved({v: variant(v) for v in names}, repeats=repeats, warmup=0, statistic=STATISTIC,
                min_time=args.min_time, max_repeats=MAX_REPEATS)
    fastest = {v: pick(r, "wall", STATISTIC) for v, r in runs.items()}
    t = {v: f["wall"] for v, f in fastest.items()}

    memory = None
    if args.memory:
        release_free_memory()
        memory_repeats = min(args.memory_repeats, args.heavy_repeats) if heavy else args.memory_repeats
        memory = {v: measure_memory_repeated(size, solver, K, v, args, memory_repeats,
                                           f"{OMP_POLICY_OPTION}={_OMP_POLICY_ARG}")
                  for v in names if v in MEMORY_VARIANTS}
    mem = {v: (m or {}).get("peak_rss_increase_mib") for v, m in (memory or {}).items()}

    def ratio(a, b):
        return None if a is None or b is None or b <= 0 else a / b

    ratios = {
        "time_unrolled_over_implicit": t["unrolled"] / t["implicit"],
        "memory_unrolled_over_implicit": ratio(mem.get("unrolled"), mem.get("implicit")),
        "engine_speedup_petsc_over_batched": t["implicit_petsc"] / t["implicit_batched"],
    }
    if "unrolled_checkpointed" in t:
        ratios["checkpointed_time_over_unrolled"] = t["unrolled_checkpointed"] / t["unrolled"]
        ratios["checkpointed_memory_over_unrolled"] = ratio(mem.get("unrolled_checkpointed"), mem.get("unrolled"))
    return {
        "size": size,
        "dofs": n,
        "solver": solver,
        "K": K,
        "B": batch,
        "repeats": len(runs[names[0]]),
        "heavy": heavy,
        "engines": engines,
        "times_s": {v: fastest[v]["wall"] for v in names},
        "times_split_s": {v: {"forward": fastest[v]["forward"], "backward": fastest[v]["backward"]}
                          for v in names},
        "all_repeats_s": {v: [r["wall"] for r in runs[v]] for v in names},
        "memory": memory,
        "stored_iterates_mib": stored_bytes(solver, K, n, batch) / MIB,
        "checkpoint_max_unrolled_values": limit if largest_k else None,
        "checkpoint_limit_mib": limit * 8 / MIB if largest_k else None,
        "ratios": ratios,
        "check": check,
    }


def bench_size(size: str, args: argparse.Namespace, skipped: list) -> tuple[dict, list]:
    h = MESH_SIZES[size]
    t0 = time.perf_counter()
    msh, prob = build_problem(h)
    if args.memory:
        # The same mesh as a file for the memory subprocesses: reading it takes 0.8 s where
        # meshing the 66k DOF size takes 5 s, in each of 20 subprocesses.
        args.msh_files[size] = str(fempdl.core.meshgen.write_msh("lshape", Path(args.msh_dir) / f"{size}.msh", h=h))
    n = prob.output_size
    mesh_info = {"h": h, "dofs": n, "cells": msh.mesh.topology.index_map(msh.tdim).size_local,
                 "mesh_seconds": time.perf_counter() - t0}
    F, W = make_inputs(args.seed, args.batch, prob.control_size("f"), n)
    k_max = max(args.ks)
    results = []
    for solver in args.solvers:
        layers = {v: make_layer(prob, solver, args.ks[0], v, args.batch) for v in VARIANTS}
        for K in args.ks:
            release_free_memory()
            stored = stored_bytes(solver, K, n, args.batch)
            available = available_memory()
            if UNROLLED_MEMORY_BOUND * stored > available:
                need = UNROLLED_MEMORY_BOUND * stored / 2 ** 30
                reason = (f"the unrolled call would need up to {need:.1f} GiB, {available / 2 ** 30:.1f} GiB "
                          "available; use a smaller --batch or --ks")
                skipped.append({"size": size, "solver": solver, "K": K, "reason": reason})
                print(f"{size:<6}{n:>6} {solver:<7}{K:>4}{args.batch:>4}  skipped: {reason}", flush=True)
                continue
            heavy = stored > args.heavy_gib * 2 ** 30
            row = bench_config(layers, size, solver, K, F, W, args, heavy, K == k_max)
            args.report.sample_load(f"after {size} {solver} K={K}")
            results.append(row)
            print_row(row, flush=True)
        for layer in layers.values():
            layer.close()
        del layers
        gc.collect()
    return mesh_info, results


# ---------------------------------------------------------------------- CLI
def parse_args(argv=None) -> argparse.Namespace:
    parser = bench_common.parser(__file__, __doc__.split("\n\n")[0], repeats=3, quick_repeats=1,
                                 quick="small mesh, K=5,20, B=8, no memory subprocesses (explicit flags still win)")
    parser.add_argument("--sizes", type=comma_list(str), help="mesh sizes: small,large (default both)")
    parser.add_argument("--ks", type=comma_list(int),
                        help="iteration caps K (default 5,20,100); the checkpointed variant runs at the largest")
    parser.add_argument("--batch", type=int, help="batch size B (default 32)")
    parser.add_argument("--solvers", type=comma_list(str),
                        help="jacobi (Richardson+Jacobi) and/or cg (CG+Jacobi); default both")
    parser.add_argument("--heavy-repeats", type=int,
                        help="timed repeats (and at most as many memory measurements) of configurations "
                             "whose unrolled call stores more than --heavy-gib of iterates (default 1)")
    parser.add_argument("--heavy-gib", type=float, default=2.0,
                        help="stored-iterate size above which a configuration is heavy (default 2 GiB: "
                             "the 66k DOF, K=100 ones at B=32)")
    parser.add_argument("--min-time", type=float,
                        help="repeat cheap configurations until their repeats add up to this many seconds "
                             "(default 1.0; 0 with --quick)")
    parser.add_argument("--memory", action=argparse.BooleanOptionalAction, default=None,
                        help="measure peak memory in subprocesses (default on; off with --quick)")
    parser.add_argument("--memory-repeats", type=int,
                        help="fresh-process memory measurements per variant, the minimum reported (default 2; "
                             "heavy configurations at most --heavy-repeats)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the random sources and weights")
    parser.add_argument("--threads", type=int,
                        help="torch threads (default: torch's own choice; the batched engine and unrolled "
                             "mode use them, PETSc runs on one)")
    parser.add_argument(OMP_POLICY_OPTION, choices=("passive", "default"), default="passive",
                        help="OpenMP wait policy: passive (default; OMP_WAIT_POLICY=PASSIVE unless the "
                             "environment sets it) or the runtime's default; write it as "
                             f"{OMP_POLICY_OPTION}=VALUE")
    parser.add_argument("--child", help=argparse.SUPPRESS)   # internal: one memory measurement
    args = parser.parse_args(argv)
    if args.child is not None:
        return args
    defaults = ({"sizes": ["small"], "ks": [5, 20], "batch": 8, "heavy_repeats": 1,
                 "memory_repeats": 1, "min_time": 0.0, "memory": False, "solvers": list(SOLVERS)} if args.quick
                else {"sizes": ["small", "large"], "ks": [5, 20, 100], "batch": 32,
                      "heavy_repeats": 1, "memory_repeats": 2, "min_time": 1.0, "memory": True,
                      "solvers": list(SOLVERS)})
    apply_defaults(parser, args, defaults, MESH_SIZES, SOLVERS)
    if min(args.batch, args.repeats, args.heavy_repeats, args.memory_repeats) < 1 or args.min_time < 0 \
            or not args.heavy_gib > 0:
        parser.error("--batch, --repeats, --heavy-repeats and --memory-repeats must be >= 1, --min-time >= 0, "
                     "--heavy-gib > 0")
    return args


def main(argv=None) -> int:
    args = parse_args(argv)
    if args.child is not None:
        return child_main(json.loads(args.child))
    if MPI.COMM_WORLD.size > 1:
        print("bench_unrolled.py measures serial runs (unrolled mode is serial); run it without mpirun",
              file=sys.stderr)
        return 2
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    started = time.perf_counter()
    settings = {
            "sizes": args.sizes, "ks": args.ks, "batch": args.batch, "solvers": args.solvers,
            "heavy_repeats": args.heavy_repeats, "heavy_gib": args.heavy_gib,
            "memory_repeats": args.memory_repeats,
            "heavy_note": (f"configurations whose unrolled call stores more than {args.heavy_gib} GiB of "
                           f"iterates ran {args.heavy_repeats} timed repeat(s) instead of {args.repeats}, and "
                           f"{min(args.memory_repeats, args.heavy_repeats)} memory measurement(s) per variant "
                           f"instead of {args.memory_repeats} (rows with heavy = true), to keep the full run "
                           "near 10 minutes"),
            "min_time_s": args.min_time, "max_repeats": MAX_REPEATS, "seed": args.seed,
            "memory_measured": args.memory,
            "checkpoint_limit": "unrolled.checkpointed_values", "agreement_tolerance": AGREEMENT_TOL,
            "problem": "poisson on lshape, control f, u = 0 on the whole boundary",
            "loss": "sum(u * W), W standard normal; F standard normal",
            "variants": {v: {"diff": d, "engine": e, "checkpointed": c} for v, (d, e, c) in VARIANTS.items()},
            "memory_method": ("peak RSS increase during one forward+backward call, in a fresh subprocess per "
                              "measurement after a two-sample warm-up: the peak mark (VmHWM) after the call "
                              "minus VmRSS before it, the mark reset through /proc/self/clear_refs"),
            "unrolled_memory_bound": UNROLLED_MEMORY_BOUND,
    }
    print(HEADER)
    with bench_common.report(__file__, args.out, statistic=STATISTIC, repeats=args.repeats, settings=settings,
                             meshes={}, results=[], skipped=[]) as report, \
            tempfile.TemporaryDirectory(prefix="bench_unrolled_") as msh_dir:
        args.msh_dir, args.msh_files, args.report = msh_dir, {}, report
        for size in args.sizes:
            mesh_info, rows = bench_size(size, args, report["skipped"])
            report["meshes"][size] = mesh_info
            report["results"].extend(rows)
        report["duration_s"] = time.perf_counter() - started
    print(f"t u/i = unrolled / implicit time (default engine); m u/i = their peak-RSS increases (MiB columns), "
          f"stored = theoretical stored iterates (MiB); p/b = implicit engine='petsc' / engine='batched' time; "
          f"ckpt = checkpointed unrolled (max_unrolled_values = checkpointed_values) over plain "
          f"unrolled, at the largest K; du, dgrad = max relative difference unrolled vs implicit; times are "
          f"the {STATISTIC} over repeats (column 'reps'); torch threads {torch.get_num_threads()}; "
          f"took {report['duration_s']:.0f} s; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
