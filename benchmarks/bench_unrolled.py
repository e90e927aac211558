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
table is printed.
"""
from __future__ import annotations

import argparse
import gc
import json
import os
import resource
import subprocess
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
import numpy as np  # noqa: E402
import torch  # noqa: E402

import fempdl.core.mesh  # noqa: E402
import fempdl.core.meshgen  # noqa: E402
import fempdl.forms  # noqa: E402
from fempdl.bridge_torch import SolveLayer  # noqa: E402
from fempdl.core.resources import available_memory  # noqa: E402
from fempdl.iterative import unrolled  # noqa: E402
from fempdl.ksp_adjoint import KSPOptions  # noqa: E402

import bench_common  # noqa: E402
from bench_common import apply_defaults, comma_list, interleaved, pick, timed  # noqa: E402

MESH_SIZES = {"small": 0.03, "large": 0.0073}   # h -> about 4k and 66k P1 DOFs (fempdl.core.meshgen)
SOLVERS = ("jacobi", "cg")                      # Richardson+Jacobi, CG+Jacobi
UNROLLED_METHOD = {"jacobi": "jacobi", "cg": "cg"}  # their fempdl.iterative.unrolled method names
AGREEMENT_TOL = 1e-12           # relative; forward always, gradients for Jacobi
ROUND_OFF = 1e-15               # relative perturbation of F that measures the output's round-off sensitivity
SENSITIVITY_FACTOR = 10         # forward tolerance: max(AGREEMENT_TOL, this * that sensitivity)
STATISTIC = "min"
MAX_REPEATS = 20
CHILD_TIMEOUT_S = 900
CHILD_MARK = "BENCH_UNROLLED_CHILD_RESULT "
WARMUP_BATCH = 2               # memory children warm up on this many samples
# Variants: (diff, engine, checkpointed). "implicit" and "unrolled" use the default engine.
VARIANTS = {
    "implicit": ("implicit", "auto", False),
    "unrolled": ("unrolled", "auto", False),
    "implicit_batched": ("implicit", "batched", False),
    "implicit_petsc": ("implicit", "petsc", False),
    "unrolled_checkpointed": ("unrolled", "auto", True),
}
MEMORY_VARIANTS = ("implicit", "unrolled", "unrolled_checkpointed")
MIB = 2.0 ** 20
# Peak RSS increase of an unrolled call over its stored_values * 8 bytes: measured 0.6-1.05 for
# Jacobi and up to 1.9 for CG (K=100, both meshes); a configuration is skipped when this bound
# times the stored size does not fit in MemAvailable.
UNROLLED_MEMORY_BOUND = 2.5


def solver_options(solver: str, max_it: int, engine: str) -> KSPOptions:
    if solver == "jacobi":
        return KSPOptions(max_it=max_it, engine=engine)
    return KSPOptions.preset(solver, max_it=max_it, engine=engine)


def build_problem(mesh):
    """The benchmark problem on ``fempdl.core.mesh.load("lshape", h=mesh)``, or on a ``.msh`` path."""
    msh = fempdl.core.mesh.load(mesh) if isinstance(mesh, str) else fempdl.core.mesh.load("lshape", h=mesh)
    return msh, fempdl.forms.poisson.problem(msh, controls=("f",))


def make_inputs(seed: int, batch: int, n_control: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random sources F (leaf, requires grad) and loss weights W; the same in parent and children."""
    rng = np.random.default_rng(seed)
    F = torch.from_numpy(rng.standard_normal((batch, n_control))).requires_grad_()
    W = torch.from_numpy(rng.standard_normal((batch, n_out)))
    return F, W


def stored_bytes(solver: str, K: int, n: int, batch: int) -> int:
    return unrolled.stored_values(UNROLLED_METHOD[solver], K, n, batch) * 8


def checkpoint_limit(solver: str, K: int, n: int, batch: int) -> int:
    """The least max_unrolled_values a checkpointed solve fits in."""
    return unrolled.checkpointed_values(UNROLLED_METHOD[solver], K, n, batch)


def make_layer(prob, solver: str, K: int, variant: str, batch: int) -> SolveLayer:
    diff, engine, checkpointed = VARIANTS[variant]
    limit = checkpoint_limit(solver, K, prob.output_size, batch) if checkpointed else None
    return SolveLayer(prob, solver_options(solver, K, engine), diff=diff, max_unrolled_values=limit)


# ---------------------------------------------------------------- timed work
def layer_call(layer: SolveLayer, F: torch.Tensor, W: torch.Tensor) -> dict:
    """``u = layer(f=F); (u * W).sum().backward()``, timed in its two halves."""
    F.grad = None
    t0 = time.perf_counter()
    u = layer(f=F)
    t1 = time.perf_counter()
    (u * W).sum().backward()
    t2 = time.perf_counter()
    return {"u": u.detach(), "grad": F.grad, "forward": t1 - t0, "backward": t2 - t1, "wall": t2 - t0}


def max_relative_difference(X: torch.Tensor, Y: torch.Tensor) -> float:
    """max over samples of ||x_i - y_i|| / ||y_i||."""
    return float(((X - Y).norm(dim=1) / Y.norm(dim=1)).max())


# ------------------------------------------------------- memory (subprocess)
def _status_kib(key: str) -> int | None:
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith(key + ":"):
                    return int(line.split()[1])
    except OSError:
        pass
    return None


def release_free_memory() -> None:
    """Give memory freed by earlier configurations back to the system (glibc keeps it otherwise),
    so that it is available to the next one and to the memory subprocesses."""
    gc.collect()
    try:
        import ctypes

        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def _reset_peak_rss() -> bool:
    """Reset the kernel's peak-RSS mark (VmHWM, and so ru_maxrss) to the current RSS (Linux >= 4.0)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
        return True
    except OSError:
        return False


def child_main(spec: dict) -> int:
    """One memory measurement (hidden ``--child`` mode); prints a result line for the parent."""
    if spec["threads"] is not None:
        torch.set_num_threads(spec["threads"])
    _, prob = build_problem(spec["mesh"])
    F, W = make_inputs(spec["seed"], spec["batch"], prob.control_size("f"), prob.output_size)
    layer = make_layer(prob, spec["solver"], spec["K"], spec["variant"], spec["batch"])
    # Warm up on a small batch (two samples, so that engine="auto" already picks the engine the
    # full batch gets): JIT, assembly and operator copies, but little of the batch's memory.
    warm = min(WARMUP_BATCH, spec["batch"])
    layer_call(layer, F[:warm].detach().clone().requires_grad_(), W[:warm])
    gc.collect()
    reset = _reset_peak_rss()
    rss_before_kib = _status_kib("VmRSS")
    maxrss_before_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    t0 = time.perf_counter()
    call = layer_call(layer, F, W)
    wall = time.perf_counter() - t0
    maxrss_after_kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    hwm_after_kib = _status_kib("VmHWM")
    if reset and rss_before_kib is not None and hwm_after_kib is not None:
        # VmHWM is the memory map's own peak mark, which clear_refs resets. (ru_maxrss is
        # max(VmHWM, a per-process value folded in whenever a thread exits), so after
        # gmsh's or MPI's threads have exited it can still hold the meshing peak.)
        increase_kib, method = hwm_after_kib - rss_before_kib, "VmHWM after - VmRSS before (peak reset)"
    else:
        increase_kib, method = maxrss_after_kib - maxrss_before_kib, "ru_maxrss after - ru_maxrss before"
    result = {
        "peak_rss_increase_mib": increase_kib / 1024.0,
        "method": method,
        "rss_before_mib": None if rss_before_kib is None else rss_before_kib / 1024.0,
        "peak_rss_after_mib": None if hwm_after_kib is None else hwm_after_kib / 1024.0,
        "ru_maxrss_before_mib": maxrss_before_kib / 1024.0,
        "ru_maxrss_after_mib": maxrss_after_kib / 1024.0,
        "peak_reset": reset,
        "warmup_batch": warm,
        "wall_s": wall,
        "engine": dict(layer.stats.solves_by_engine),
        "finite": bool(torch.isfinite(call["u"]).all() and torch.isfinite(call["grad"]).all()),
    }
    print(CHILD_MARK + json.dumps(result), flush=True)
    return 0


def measure_memory(size: str, solver: str, K: int, variant: str, args: argparse.Namespace) -> dict:
    """Run one ``--child`` measurement in a fresh interpreter; its result or the error."""
    spec = {"mesh": args.msh_files.get(size, MESH_SIZES[size]), "solver": solver, "K": K, "variant": variant,
            "batch": args.batch, "seed": args.seed, "threads": args.threads}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--child", json.dumps(spec),
           f"{OMP_POLICY_OPTION}={_OMP_POLICY_ARG}"]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=CHILD_TIMEOUT_S)
    except subprocess.TimeoutExpired:
        return {"error": f"timed out after {CHILD_TIMEOUT_S} s"}
    for line in proc.stdout.splitlines():
        if line.startswith(CHILD_MARK):
            return json.loads(line[len(CHILD_MARK):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"error": f"child exited with {proc.returncode} (a negative code is a signal, -9 often the "
                     f"out-of-memory killer): {' | '.join(tail)}"}


def measure_memory_repeated(size: str, solver: str, K: int, variant: str, args, repeats: int) -> dict:
    """``repeats`` fresh-process measurements: the run with the smallest increase, plus all of them.

    The same call's peak RSS varies between processes (up to 2.4x for unrolled CG on the 4k mesh,
    with two modes and nothing else changed): where the allocator places and returns freed
    blocks differs from run to run. The minimum is what the call needs at least."""
    runs = []
    timed(lambda: runs.append(measure_memory(size, solver, K, variant, args)), repeats=repeats, warmup=0)
    good = [r for r in runs if "error" not in r]
    if not good:
        return runs[0]
    best = pick(good, "peak_rss_increase_mib", "min")
    samples = best.pop("peak_rss_increase_mib_samples")
    best.update(samples_mib=samples, max_mib=max(samples), failed_runs=len(runs) - len(good))
    return best


# --------------------------------------------------------------- one config
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
        memory = {v: measure_memory_repeated(size, solver, K, v, args, memory_repeats)
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


def round_off_sensitivity(layer: SolveLayer, F: torch.Tensor, u: torch.Tensor) -> float:
    """How much the K-step output moves when F is perturbed at round-off level (relative 1e-15,
    random): the scale below which two implementations of the same iteration cannot agree."""
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        noise = torch.randn(F.shape, generator=generator, dtype=F.dtype)
        u_perturbed = layer(f=F.detach() * (1.0 + ROUND_OFF * noise))
    return max_relative_difference(u_perturbed, u)


def check_outputs(warm: dict, solver: str, sensitivity: float) -> dict:
    """Differences between the variants' outputs and gradients (the warm-up calls)."""
    def diff(a, b, key):
        return max_relative_difference(warm[a][key], warm[b][key])

    check = {
        "u_unrolled_vs_implicit": diff("unrolled", "implicit", "u"),
        "grad_unrolled_vs_implicit": diff("unrolled", "implicit", "grad"),
        "u_unrolled_vs_implicit_petsc": diff("unrolled", "implicit_petsc", "u"),
        "grad_unrolled_vs_implicit_petsc": diff("unrolled", "implicit_petsc", "grad"),
        "u_petsc_vs_batched": diff("implicit_petsc", "implicit_batched", "u"),
        "grad_petsc_vs_batched": diff("implicit_petsc", "implicit_batched", "grad"),
    }
    if "unrolled_checkpointed" in warm:
        check["u_checkpointed_vs_unrolled"] = diff("unrolled_checkpointed", "unrolled", "u")
        check["grad_checkpointed_vs_unrolled"] = diff("unrolled_checkpointed", "unrolled", "grad")
    # Checked: unrolled against the same iteration in the other mode (default engine) and against
    # its checkpointed self; for Jacobi also against PETSc's KSP (round-off stays ~1e-16 there).
    # Recorded only: CG against PETSc's KSPCG (round-off grows with K), CG gradients (implicit is
    # not the VJP of the capped CG map, by design).
    u_keys = ["u_unrolled_vs_implicit"]
    grad_keys = []
    if solver == "jacobi":
        u_keys += ["u_unrolled_vs_implicit_petsc", "u_petsc_vs_batched"]
        grad_keys += ["grad_unrolled_vs_implicit", "grad_unrolled_vs_implicit_petsc", "grad_petsc_vs_batched"]
    if "unrolled_checkpointed" in warm:
        u_keys.append("u_checkpointed_vs_unrolled")
        grad_keys.append("grad_checkpointed_vs_unrolled")
    check["u_change_from_round_off_perturbation"] = sensitivity
    check["tolerance"] = AGREEMENT_TOL
    check["forward_tolerance"] = max(AGREEMENT_TOL, SENSITIVITY_FACTOR * sensitivity)
    check["forward_checked"] = u_keys
    check["forward_agrees"] = all(check[k] <= check["forward_tolerance"] for k in u_keys)
    check["gradients_checked"] = grad_keys
    check["gradients_agree"] = all(check[k] <= AGREEMENT_TOL for k in grad_keys)
    return check


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


# ------------------------------------------------------------------- output
HEADER = (f"{'size':<6}{'dofs':>6} {'solver':<7}{'K':>4}{'B':>4} {'impl s':>8}{'unrl s':>8}{'t u/i':>7} "
          f"{'impl MiB':>9}{'unrl MiB':>9}{'m u/i':>7}{'stored':>8} "
          f"{'petsc s':>8}{'batch s':>8}{'p/b':>6} {'ckpt t/u':>8}{'ckpt m/u':>9} "
          f"{'du':>8}{'dgrad':>8}{'reps':>5}")


def _fmt(value, width: int, spec: str) -> str:
    return f"{'-':>{width}}" if value is None else f"{value:>{width}{spec}}"


def print_row(row: dict, flush: bool = False) -> None:
    t, r, c = row["times_s"], row["ratios"], row["check"]
    mem = row["memory"] or {}
    mi = mem.get("implicit", {}).get("peak_rss_increase_mib")
    mu = mem.get("unrolled", {}).get("peak_rss_increase_mib")
    du = max(c["u_unrolled_vs_implicit"], c["u_unrolled_vs_implicit_petsc"])
    print(f"{row['size']:<6}{row['dofs']:>6} {row['solver']:<7}{row['K']:>4}{row['B']:>4} "
          f"{t['implicit']:>8.3f}{t['unrolled']:>8.3f}{r['time_unrolled_over_implicit']:>7.2f} "
          f"{_fmt(mi, 9, '.1f')}{_fmt(mu, 9, '.1f')}{_fmt(r['memory_unrolled_over_implicit'], 7, '.1f')}"
          f"{row['stored_iterates_mib']:>8.0f} "
          f"{t['implicit_petsc']:>8.3f}{t['implicit_batched']:>8.3f}"
          f"{r['engine_speedup_petsc_over_batched']:>6.2f} "
          f"{_fmt(r.get('checkpointed_time_over_unrolled'), 8, '.2f')}"
          f"{_fmt(r.get('checkpointed_memory_over_unrolled'), 9, '.3f')} "
          f"{du:>8.1e}{c['grad_unrolled_vs_implicit']:>8.1e}{row['repeats']:>5}"
          + ("" if c["forward_agrees"] and c["gradients_agree"] else "  CHECK FAILED"),
          flush=flush)


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
