"""Benchmark: the batched Richardson-Jacobi solve against a memory-bandwidth floor.

Poisson on the bundled L-shape (about 66k P1 DOFs, h=0.0073, as in
``benchmarks/bench_krylov.py``), the source f as control, B=32 random sources,
Richardson + Jacobi capped at K=200 on the batched engine. One timed call is
``u = layer(f=F); (u * W).sum().backward()``: K sweeps for the forward solves
and K for the transposed (adjoint) solves, all B columns at once.

Floor. A Jacobi sweep X <- c + (I - D^-1 A) X for B columns must at least read
the matrix once (values and column indices, 12 bytes per nonzero, plus 4 bytes
per row pointer) and read X and c and write the new X once
(3 * 8 * n * B bytes). The floor is 2 K such sweeps at the machine's stream
bandwidth: the STREAM triad a = b + s c, torch on all its threads, arrays of
2^25 doubles (four times the L3 cache and more), 3 * 8 bytes per element
(STREAM's count, no write-allocate), best of 20, measured before and after the
timed calls (the higher one counts: it gives the stricter floor). Printed and recorded: the
floor, the measured call, their ratio (target at most 2), the iterations'
share of the call (the engine's own timer), and PETSc's per-sample loop on the
same call for scale. The bandwidth at the iterate's own size (cache-resident)
is recorded too: a sweep whose iterates stay in cache can beat the floor.

Run on an idle machine::

    .venv/bin/python benchmarks/bench_floor.py
    .venv/bin/python benchmarks/bench_floor.py --quick --out /tmp/floor.json   # 4k DOFs, 2 repeats
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # before torch loads OpenMP

import time

import numpy as np  # noqa: E402
import torch  # noqa: E402

import fempdl.core.mesh  # noqa: E402
import fempdl.forms  # noqa: E402
from fempdl.bridge_torch import SolveLayer  # noqa: E402
from fempdl.ksp_adjoint import KSPOptions  # noqa: E402

import bench_common  # noqa: E402
from bench_common import interleaved, reduce, timed  # noqa: E402

TARGET = 2.0
STREAM_ELEMENTS = 2 ** 25


def triad_bandwidth(elements: int, repeats: int = 20) -> float:
    """Bytes per second of a = b + 0.5 c on ``elements`` doubles (STREAM's 24 bytes per element)."""
    b = torch.rand(elements, dtype=torch.float64)
    c = torch.rand(elements, dtype=torch.float64)
    a = torch.empty_like(b)
    return 24 * elements / timed(lambda: torch.add(b, c, alpha=0.5, out=a), repeats=repeats, warmup=0).seconds


def sweep_bytes(n: int, nnz: int, batch: int) -> int:
    """Least memory traffic of one Jacobi sweep for ``batch`` columns: the matrix once, X and c read, X written."""
    return 12 * nnz + 4 * (n + 1) + 3 * 8 * n * batch


def call(layer, F, W) -> float:
    F.grad = None
    layer.stats.reset()
    t0 = time.perf_counter()
    u = layer(f=F)
    (u * W).sum().backward()
    return time.perf_counter() - t0


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=5,
                                 quick="h = 0.03 (4k DOFs)", quick_repeats=2)
    parser.add_argument("--h", type=float, default=0.0073, help="mesh size of the L-shape (0.0073: 66k DOFs)")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--batch", type=int, default=32)
    args = parser.parse_args(argv)
    if args.quick:
        args.h = 0.03
    with bench_common.report(__file__, args.out, repeats=args.repeats) as data:
        measure(args, data)
    return 0


def measure(args, data: bench_common.Report) -> None:
    msh = fempdl.core.mesh.load("lshape", h=args.h)
    prob = fempdl.forms.poisson.problem(msh, controls=("f",), g=lambda x: 1.0 + x[0] * x[1])
    rng = np.random.default_rng(0)
    F = torch.from_numpy(rng.standard_normal((args.batch, prob.control_size("f")))).requires_grad_()
    W = torch.from_numpy(rng.standard_normal((args.batch, prob.output_size)))
    layers = {e: SolveLayer(prob, KSPOptions(max_it=args.k, engine=e)) for e in ("batched", "petsc")}
    A = layers["batched"].system.constant_matrix()
    n, nnz = A.shape[0], A.nnz

    stream_before = triad_bandwidth(STREAM_ELEMENTS)
    iteration_times = []

    def batched() -> float:
        seconds = call(layers["batched"], F, W)
        iteration_times.append(layers["batched"].stats.forward_time + layers["batched"].stats.backward_time)
        return seconds

    # warm-up: JIT, assembly, operator copies; then the engines alternate, in alternating order
    timings = interleaved({"batched": batched, "petsc": lambda: call(layers["petsc"], F, W)},
                          repeats=args.repeats, alternate=True, report=data)
    iteration_times = iteration_times[1:]                    # not the warm-up's
    times = {e: list(t.samples) for e, t in timings.items()}
    stream_after = triad_bandwidth(STREAM_ELEMENTS)
    stream = max(stream_before, stream_after)          # the higher bandwidth gives the lower, stricter floor
    in_cache = triad_bandwidth(n * args.batch)
    traffic = 2 * args.k * sweep_bytes(n, nnz, args.batch)
    floor = traffic / stream
    best = {e: t.seconds for e, t in timings.items()}
    iterations = reduce(iteration_times)
    ratio = best["batched"] / floor
    print(f"n={n} nnz={nnz} B={args.batch} K={args.k}: {2 * args.k} sweeps x "
          f"{sweep_bytes(n, nnz, args.batch) / 1e6:.1f} MB = {traffic / 1e9:.2f} GB")
    print(f"stream triad {stream / 1e9:.1f} GB/s (before the calls {stream_before / 1e9:.1f}, after "
          f"{stream_after / 1e9:.1f}; in cache at the iterate's size: {in_cache / 1e9:.1f} GB/s)")
    print(f"floor {floor:.3f} s, batched call {best['batched']:.3f} s (iterations {iterations:.3f} s): "
          f"{ratio:.2f}x the floor (target <= {TARGET}); "
          f"per right-hand side {1e3 * best['batched'] / args.batch:.1f} ms "
          f"against {1e3 * floor / args.batch:.1f} ms; PETSc loop {best['petsc']:.3f} s "
          f"({best['petsc'] / best['batched']:.2f}x slower)")
    data.update({"torch_threads": torch.get_num_threads(),
            "problem": "poisson on lshape, control f, g = 1 + x*y; Richardson + Jacobi, batched engine; "
                       "one call = B forward + B transposed capped solves",
            "dofs": n, "nnz": nnz, "B": args.batch, "K": args.k,
            "bytes_model": "per sweep: 12 nnz + 4 (n + 1) + 3 * 8 n B (matrix once; read X and c, write X); "
                           "2 K sweeps per call",
            "bytes_per_call": traffic, "stream_triad_bytes_per_s": stream, "stream_elements": STREAM_ELEMENTS,
            "stream_triad_before_and_after_bytes_per_s": [stream_before, stream_after],
            "triad_bytes_per_s_at_iterate_size": in_cache,
            "floor_seconds": floor, "batched_seconds_min": best["batched"], "iteration_seconds_min": iterations,
            "ratio_to_floor": ratio, "iterations_ratio_to_floor": iterations / floor, "target_ratio": TARGET,
            "petsc_loop_seconds_min": best["petsc"], "speedup_over_petsc_loop": best["petsc"] / best["batched"],
            "seconds_all": times})
    for layer in layers.values():
        layer.close()


if __name__ == "__main__":
    raise SystemExit(main())
