"""Peak memory of one bench_unrolled.py call, measured in a fresh process per measurement.

The parent side (:func:`measure_memory_repeated`, :func:`measure_memory`) runs ``bench_unrolled.py
--child SPEC`` and reads the result line it prints; the child side (:func:`child_main`) builds the
problem and layer, warms up on two samples, resets the kernel's peak-RSS mark and reports the peak
increase of one forward + backward call. :func:`release_free_memory` hands freed memory back to the
system between configurations.
"""
from __future__ import annotations

import gc
import json
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch
from unrolled_cases import MESH_SIZES, build_problem, layer_call, make_inputs, make_layer

from bench_common import pick, timed

SCRIPT = Path(__file__).resolve().parent / "bench_unrolled.py"   # the benchmark, whose --child runs child_main
CHILD_TIMEOUT_S = 900
CHILD_MARK = "BENCH_UNROLLED_CHILD_RESULT "
WARMUP_BATCH = 2               # memory children warm up on this many samples


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


def measure_memory(size: str, solver: str, K: int, variant: str, args, omp_policy: str) -> dict:
    """Run one ``--child`` measurement in a fresh interpreter; its result or the error. ``omp_policy``: the
    child's ``--omp-wait-policy=...`` argument (the parent's)."""
    spec = {"mesh": args.msh_files.get(size, MESH_SIZES[size]), "solver": solver, "K": K, "variant": variant,
            "batch": args.batch, "seed": args.seed, "threads": args.threads}
    cmd = [sys.executable, str(SCRIPT), "--child", json.dumps(spec), omp_policy]
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


def measure_memory_repeated(size: str, solver: str, K: int, variant: str, args, repeats: int,
                            omp_policy: str) -> dict:
    """``repeats`` fresh-process measurements: the run with the smallest increase, plus all of them.

    The same call's peak RSS varies between processes (up to 2.4x for unrolled CG on the 4k mesh,
    with two modes and nothing else changed): where the allocator places and returns freed
    blocks differs from run to run. The minimum is what the call needs at least."""
    runs = []
    timed(lambda: runs.append(measure_memory(size, solver, K, variant, args, omp_policy)), repeats=repeats, warmup=0)
    good = [r for r in runs if "error" not in r]
    if not good:
        return runs[0]
    best = pick(good, "peak_rss_increase_mib", "min")
    samples = best.pop("peak_rss_increase_mib_samples")
    best.update(samples_mib=samples, max_mib=max(samples), failed_runs=len(runs) - len(good))
    return best

