"""Resource bounds as measured: the memory and backward cost of unrolled solves, and the cost of the Ctrl-C monitor.

(1) Unrolled CG + Jacobi (``SolveLayer(diff="unrolled", max_unrolled_values=
    unrolled.checkpointed_values(...))``, the least bound a checkpointed solve
    fits in) on the bundled L-shape (1481 DOFs), B = 8, one torch thread, for
    each K of ``--ks``, each in a child process: the RSS increase over the
    forward pass (what the graph keeps) and the peak RSS increase over forward
    + backward, against that bound (x 8 bytes) and ``stored_values * 8`` (what
    the unbounded solve keeps). ``--unbounded-k`` adds one run without the
    bound, for contrast.
(2) On the L-shape at h = 0.0073 (65,558 DOFs), B = 32, torch's default
    threads: Richardson + Jacobi K = 100, CG + Jacobi K = 20 and K = 100
    unbounded, and CG K = 100 bounded as in (1). Forward and backward seconds
    (the better of two calls, ``bench_common.timed``), the backward / forward ratio (target <= 2) and
    the peak RSS increase against the bound (CG K = 100 bounded: target 4 GB).
(3) Richardson + Jacobi capped at ``--monitor-k`` iterations on the L-shape at
    h = 0.1 and 0.03 (408 and 4071 DOFs), one sample on the PETSc engine, with
    and without the KSP monitor that lets Ctrl-C stop a long solve (fempdl
    installs it where the cap times the unknowns reaches
    ``fempdl.core.tuning.INTERRUPT_CHECK_MIN_WORK``): seconds per iteration,
    the minimum over ``--repeats`` alternating runs (``bench_common.interleaved``).

Writes ``bench-results/bench_bounds.json`` (``--out``) through ``bench_common.report``; ``--quick``
runs section (1) at K = 1000 and section (3) at K = 500.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time

from mpi4py import MPI
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import tuning
from fempdl.iterative import unrolled
from fempdl.ksp_adjoint import KSPOptions

import bench_common
from bench_common import comma_list, interleaved, reduce, timed

MIB = 2.0 ** 20
BATCH = 8
CHILD_MARK = "BENCH_BOUNDS_CHILD "
MONITOR_MESH_SIZES = (0.1, 0.03)        # L-shape: 408 and 4071 DOFs
LARGE = {"h": 0.0073, "batch": 32, "threads": 0}
LARGE_RUNS = [("jacobi", 100, False), ("cg", 20, False), ("cg", 100, False), ("cg", 100, True)]
METHOD = {"jacobi": "jacobi", "cg": "cg"}


def rss_mib() -> float:
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / MIB


def child(spec: dict) -> dict:
    """Unrolled forward + backward in this process (twice; the better time of each); RSS figures in MiB."""
    if spec["threads"]:
        torch.set_num_threads(spec["threads"])
    K, batch, solver, bounded = spec["K"], spec["batch"], spec["solver"], spec["bounded"]
    msh = mesh.load("lshape", MPI.COMM_SELF, **({"h": spec["h"]} if spec["h"] else {}))
    prob = forms.poisson.problem(msh, controls=("f",))
    n = prob.output_size
    bound = unrolled.checkpointed_values(METHOD[solver], K, n, batch)
    options = KSPOptions.preset("cg", max_it=K) if solver == "cg" else KSPOptions(max_it=K)
    layer = SolveLayer(prob, options, diff="unrolled", max_unrolled_values=bound if bounded else None)
    f = torch.randn(batch, prob.control_size("f"), dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    f.requires_grad_()
    with torch.no_grad():
        layer(f=f)                          # warm-up: the torch operators are built, no graph is kept
    start = rss_mib()
    forward, backward, kept = [], [], []

    def forward_and_backward() -> None:
        t0 = time.perf_counter()
        u = layer(f=f)
        kept.append(rss_mib() - start)
        t1 = time.perf_counter()
        (u * u).sum().backward()
        backward.append(time.perf_counter() - t1)
        forward.append(t1 - t0)
        f.grad = None

    timed(forward_and_backward, repeats=2, warmup=0)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return {"K": K, "solver": solver, "bounded": bounded, "n": n, "batch": batch,
            "torch_threads": torch.get_num_threads(),
            "max_unrolled_values": bound if bounded else None,
            "start_rss_mib": start, "forward_rss_increase_mib": kept[0],
            "peak_rss_mib": peak, "peak_rss_increase_mib": peak - start,
            "bound_mib": bound * 8 / MIB,
            "unbounded_stored_mib": unrolled.stored_values(METHOD[solver], K, n, batch) * 8 / MIB,
            "forward_s": reduce(forward), "backward_s": reduce(backward),
            "backward_over_forward": reduce(backward) / reduce(forward),
            "forward_s_all": forward, "backward_s_all": backward}


def run_child(spec: dict, timeout: float) -> dict:
    done = subprocess.run([sys.executable, __file__, "--child", json.dumps(spec)],
                          capture_output=True, text=True, timeout=timeout,
                          env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    if done.returncode != 0:
        raise RuntimeError(f"child {spec} failed:\n{done.stderr}")
    line = next(line for line in done.stdout.splitlines() if line.startswith(CHILD_MARK))
    return json.loads(line[len(CHILD_MARK):])


def report(row: dict) -> None:
    print(f"unrolled {row['solver']} n={row['n']} B={row['batch']} K={row['K']:>6} "
          f"{'bounded' if row['bounded'] else 'unbounded'}: forward keeps {row['forward_rss_increase_mib']:.0f} MiB, "
          f"peak +{row['peak_rss_increase_mib']:.0f} MiB, bound {row['bound_mib']:.0f} MiB, unbounded would keep "
          f"{row['unbounded_stored_mib']:.0f} MiB; forward {row['forward_s']:.2f} s, backward "
          f"{row['backward_s']:.2f} s ({row['backward_over_forward']:.2f}x)", flush=True)


def monitor_cost(K: int, repeats: int, h: float) -> dict:
    """Seconds per Richardson + Jacobi iteration with and without the interrupt monitor, on the L-shape at h."""
    torch.set_num_threads(1)
    prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=h), controls=("f",))
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    threshold = tuning.INTERRUPT_CHECK_MIN_WORK
    layers = {name: SolveLayer(prob, KSPOptions(max_it=K, engine="petsc")) for name in ("with_monitor",
                                                                                          "without_monitor")}

    def per_iteration(name: str):
        def run() -> float:
            tuning.INTERRUPT_CHECK_MIN_WORK = 0 if name == "with_monitor" else 10 ** 30
            before = layers[name].stats.forward_time
            layers[name](f=f)
            return (layers[name].stats.forward_time - before) / K
        return run

    timings = interleaved({name: per_iteration(name) for name in layers}, repeats=repeats, warmup=0)
    tuning.INTERRUPT_CHECK_MIN_WORK = threshold
    best = {name: t.seconds for name, t in timings.items()}
    times = {name: list(t.samples) for name, t in timings.items()}
    return {"K": K, "h": h, "n": prob.output_size, "repeats": repeats, "seconds_per_iteration_min": best,
            "seconds_per_iteration_all": times,
            "monitor_overhead_per_iteration_s": best["with_monitor"] - best["without_monitor"],
            "monitor_overhead_fraction": best["with_monitor"] / best["without_monitor"] - 1.0,
            "installed_from_max_it_times_unknowns": threshold}


def main() -> None:
    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=7,
                                 quick="K = 1000 only, no unbounded run, no 66k-DOF runs, monitor K = 500")
    parser.add_argument("--ks", type=comma_list(int), default=[1000, 4000, 20000])
    parser.add_argument("--unbounded-k", type=int, default=1000)
    parser.add_argument("--large", action=argparse.BooleanOptionalAction, default=True,
                        help="section (2), the 66k-DOF runs (needs about 8 GB free)")
    parser.add_argument("--monitor-k", type=int, default=2000)
    parser.add_argument("--timeout", type=float, default=1800.0)
    parser.add_argument("--child", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.child is not None:
        print(CHILD_MARK + json.dumps(child(json.loads(args.child))))
        return
    if args.quick:
        args.ks, args.unbounded_k, args.large, args.monitor_k = [1000], 0, False, 500
    with bench_common.report(__file__, args.out, repeats=args.repeats) as data:
        data.update(measure(args))


def measure(args) -> dict:
    small = {"h": None, "batch": BATCH, "threads": 1, "solver": "cg"}
    memory = [run_child({**small, "K": K, "bounded": True}, args.timeout) for K in args.ks]
    if args.unbounded_k:
        memory.append(run_child({**small, "K": args.unbounded_k, "bounded": False}, args.timeout))
    for row in memory:
        report(row)
    large = []
    if args.large:
        for solver, K, bounded in LARGE_RUNS:
            large.append(run_child({**LARGE, "solver": solver, "K": K, "bounded": bounded}, args.timeout))
            report(large[-1])
    costs = [monitor_cost(args.monitor_k, args.repeats, h) for h in MONITOR_MESH_SIZES]
    for cost in costs:
        print(f"interrupt monitor: {cost['seconds_per_iteration_min']['with_monitor'] * 1e6:.2f} vs "
              f"{cost['seconds_per_iteration_min']['without_monitor'] * 1e6:.2f} us per iteration "
              f"({100 * cost['monitor_overhead_fraction']:+.1f}%) at n={cost['n']}")
    return {"unrolled_memory": memory, "unrolled_large": large, "interrupt_monitor": costs}


if __name__ == "__main__":
    main()
