"""Resource bounds as measured: the memory of checkpointed unrolled solves, and the cost of the Ctrl-C monitor.

(1) Unrolled CG + Jacobi (``SolveLayer(diff="unrolled", max_unrolled_values=1000)``)
    on the bundled L-shape (1481 DOFs), B = 8, for each K of ``--ks``, each
    in a child process: the RSS increase over the forward pass (what the
    graph keeps) and the peak RSS increase over forward + backward, against
    ``fempdl.iterative.unrolled.checkpointed_values * 8`` (the bound) and
    ``stored_values * 8`` (what the unbounded solve keeps). ``--unbounded-k``
    adds one run without the bound, for contrast.
(2) Richardson + Jacobi capped at ``--monitor-k`` iterations on the L-shape at
    h = 0.1 and 0.03 (408 and 4071 DOFs), one sample on the PETSc engine, with
    and without the KSP monitor that lets Ctrl-C stop a long solve (fempdl
    installs it where the cap times the unknowns reaches
    ``fempdl.ksp_adjoint.INTERRUPT_CHECK_MIN_WORK``): seconds per iteration,
    the minimum over ``--repeats`` alternating runs.

Writes ``bench-results/bench_bounds.json`` with the machine's load.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import torch
from mpi4py import MPI

from bench_common import comma_list, machine_info, write_json_atomically
from fempdl import forms, ksp_adjoint, mesh
from fempdl.iterative import unrolled
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

MIB = 2.0 ** 20
BATCH = 8
MAX_VALUES = 1000
CHILD_MARK = "BENCH_BOUNDS_CHILD "
MONITOR_MESH_SIZES = (0.1, 0.03)        # L-shape: 408 and 4071 DOFs


def rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / MIB


def child(K: int, bounded: bool) -> dict:
    """One unrolled forward + backward in this process; RSS figures in MiB."""
    torch.set_num_threads(1)
    prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF), controls=("f",))
    layer = SolveLayer(prob, KSPOptions.preset("cg", max_it=K), diff="unrolled",
                       max_unrolled_values=MAX_VALUES if bounded else None)
    f = torch.randn(BATCH, prob.control_size("f"), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f.requires_grad_()
    with torch.no_grad():
        layer(f=f)                          # warm-up: the torch operators are built, no graph is kept
    start = rss_mib()
    t0 = time.perf_counter()
    u = layer(f=f)
    after_forward = rss_mib()
    t1 = time.perf_counter()
    (u * u).sum().backward()
    t2 = time.perf_counter()
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    n = prob.output_size
    return {"K": K, "bounded": bounded, "n": n, "batch": BATCH,
            "max_unrolled_values": MAX_VALUES if bounded else None,
            "start_rss_mib": start, "forward_rss_increase_mib": after_forward - start,
            "peak_rss_mib": peak, "peak_rss_increase_mib": peak - start,
            "bound_mib": unrolled.checkpointed_values("cg", K, n, BATCH) * 8 / MIB,
            "unbounded_stored_mib": unrolled.stored_values("cg", K, n, BATCH) * 8 / MIB,
            "forward_s": t1 - t0, "backward_s": t2 - t1}


def run_child(K: int, bounded: bool, timeout: float) -> dict:
    done = subprocess.run([sys.executable, __file__, "--child", str(K), "--child-bounded", str(int(bounded))],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    if done.returncode != 0:
        raise RuntimeError(f"child K={K} failed:\n{done.stderr}")
    line = next(line for line in done.stdout.splitlines() if line.startswith(CHILD_MARK))
    return json.loads(line[len(CHILD_MARK):])


def monitor_cost(K: int, repeats: int, h: float) -> dict:
    """Seconds per Richardson + Jacobi iteration with and without the interrupt monitor, on the L-shape at h."""
    torch.set_num_threads(1)
    prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=h), controls=("f",))
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    threshold = ksp_adjoint.INTERRUPT_CHECK_MIN_WORK
    times = {"with_monitor": [], "without_monitor": []}
    layers = {name: SolveLayer(prob, KSPOptions(max_it=K, engine="petsc")) for name in times}
    for _ in range(repeats):
        for name, layer in layers.items():
            ksp_adjoint.INTERRUPT_CHECK_MIN_WORK = 0 if name == "with_monitor" else 10 ** 30
            before = layer.stats.forward_time
            layer(f=f)
            times[name].append((layer.stats.forward_time - before) / K)
    ksp_adjoint.INTERRUPT_CHECK_MIN_WORK = threshold
    best = {name: min(values) for name, values in times.items()}
    return {"K": K, "h": h, "n": prob.output_size, "repeats": repeats, "seconds_per_iteration_min": best,
            "seconds_per_iteration_all": times,
            "monitor_overhead_per_iteration_s": best["with_monitor"] - best["without_monitor"],
            "monitor_overhead_fraction": best["with_monitor"] / best["without_monitor"] - 1.0,
            "installed_from_max_it_times_unknowns": threshold}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--ks", type=comma_list(int), default=[1000, 4000, 20000])
    parser.add_argument("--unbounded-k", type=int, default=1000)
    parser.add_argument("--monitor-k", type=int, default=2000)
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent.parent / "bench-results"
                        / "bench_bounds.json")
    parser.add_argument("--child", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--child-bounded", type=int, default=1, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(CHILD_MARK + json.dumps(child(args.child, bool(args.child_bounded))))
        return
    machine = machine_info()
    memory = [run_child(K, True, args.timeout) for K in args.ks]
    if args.unbounded_k:
        memory.append(run_child(args.unbounded_k, False, args.timeout))
    for row in memory:
        print(f"unrolled CG K={row['K']:>6} {'bounded' if row['bounded'] else 'unbounded'}: forward keeps "
              f"{row['forward_rss_increase_mib']:.1f} MiB, bound {row['bound_mib']:.1f} MiB, unbounded would keep "
              f"{row['unbounded_stored_mib']:.0f} MiB; forward {row['forward_s']:.1f} s, backward "
              f"{row['backward_s']:.1f} s")
    costs = [monitor_cost(args.monitor_k, args.repeats, h) for h in MONITOR_MESH_SIZES]
    for cost in costs:
        print(f"interrupt monitor: {cost['seconds_per_iteration_min']['with_monitor'] * 1e6:.2f} vs "
              f"{cost['seconds_per_iteration_min']['without_monitor'] * 1e6:.2f} us per iteration "
              f"({100 * cost['monitor_overhead_fraction']:+.1f}%) at n={cost['n']}")
    machine["load_average_1_5_15_min_at_end"] = list(os.getloadavg())
    write_json_atomically({"machine": machine, "unrolled_memory": memory, "interrupt_monitor": costs}, args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
