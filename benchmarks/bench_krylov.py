"""Benchmark: batched capped CG and GMRES(30) + Jacobi against PETSc's per-sample loop.

Poisson on the bundled L-shape (about 4k and 66k P1 DOFs, as in
``benchmarks/bench_layer.py``), the source f as control, B random sources, a
pure cap of K iterations, or (``cg-rtol``) CG + Jacobi to rtol 1e-8 without a cap, each column
stopping at its own tolerance. One timed call is ``u = layer(f=F); (u * W).sum().backward()``:
B forward solves and B transposed solves. The two engines (``engine="petsc"``:
one KSP solve per sample; ``engine="batched"``: all samples at once, see
:mod:`fempdl.iterative.batched`) are interleaved within every repeat (``bench_common.interleaved``); each
time reported is the minimum over the repeats, and the speed-up is
petsc / batched. The results of both engines are compared (max relative
difference of u and of dJ/df). Also recorded: the choice ``engine="auto"`` makes.

Run::

    .venv/bin/python benchmarks/bench_krylov.py     # both sizes, CG and GMRES(30), K=200, B=32 (CG also B=2,4,8),
                                                    # and CG to rtol 1e-8 at B=32
    .venv/bin/python benchmarks/bench_krylov.py --quick --out /tmp/k.json
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # before torch loads OpenMP

import functools
import time

import numpy as np  # noqa: E402
import torch  # noqa: E402

import fempdl.core.mesh  # noqa: E402
import fempdl.forms  # noqa: E402
from fempdl.bridge_torch import SolveLayer  # noqa: E402
from fempdl.ksp_adjoint import KSPOptions  # noqa: E402

import bench_common  # noqa: E402
from bench_common import comma_list  # noqa: E402

MESH_SIZES = {"small": 0.03, "large": 0.0073}
TARGET = 2.0
CONVERGED_RTOL = 1e-8


def options(solver: str, K: int, engine: str) -> KSPOptions:
    if solver == "cg-rtol":        # converged: each column stops at its own rtol, no cap
        return KSPOptions.preset("cg", rtol=CONVERGED_RTOL, engine=engine)
    if solver == "cg":
        return KSPOptions.preset("cg", max_it=K, engine=engine)
    return KSPOptions.preset("gmres", max_it=K, gmres_restart=30, engine=engine)


def call(layer, F, W):
    F.grad = None
    t0 = time.perf_counter()
    u = layer(f=F)
    (u * W).sum().backward()
    return time.perf_counter() - t0, u.detach().numpy(), F.grad.numpy().copy()


def engine_seconds(layer, F, W) -> float:
    return call(layer, F, W)[0]


def rel(X, Y) -> float:
    return float(np.max(np.linalg.norm(X - Y, axis=1) / np.linalg.norm(Y, axis=1)))


def bench(size: str, args, rng, data: bench_common.Report) -> list:
    msh = fempdl.core.mesh.load("lshape", h=MESH_SIZES[size])
    prob = fempdl.forms.poisson.problem(msh, controls=("f",), g=lambda x: 1.0 + x[0] * x[1])
    F_all = rng.standard_normal((max(args.batches), prob.control_size("f")))
    W_all = torch.from_numpy(rng.standard_normal((max(args.batches), prob.output_size)))
    rows = []
    for solver, batch in [(s, b) for s in args.solvers for b in args.batches
                          if b == max(args.batches) or s in args.small_batch_solvers]:
        F = torch.from_numpy(F_all[:batch].copy()).requires_grad_()
        W = W_all[:batch]
        layers = {e: SolveLayer(prob, options(solver, args.k, e)) for e in ("petsc", "batched", "auto")}
        _, u_p, g_p = call(layers["petsc"], F, W)          # warm-up and check
        _, u_b, g_b = call(layers["batched"], F, W)
        call(layers["auto"], F, W)
        timings = bench_common.interleaved({e: functools.partial(engine_seconds, layers[e], F, W)
                                            for e in ("petsc", "batched")},
                                           repeats=args.repeats, warmup=0, alternate=True, report=data)
        times = {e: list(t.samples) for e, t in timings.items()}
        best = {e: t.seconds for e, t in timings.items()}
        converged = solver == "cg-rtol"
        its = {e: layers[e].stats.total_iterations for e in ("petsc", "batched")}
        row = {"size": size, "dofs": prob.output_size,
               "solver": f"{solver}+jacobi" + ("(30)" if solver == "gmres" else ""),
               "K": None if converged else args.k, "rtol": CONVERGED_RTOL if converged else None,
               "iterations_fwd_plus_bwd_per_call": {e: n // (1 + args.repeats) for e, n in its.items()},
               "B": batch, "seconds_min": best, "seconds_all": times,
               "speedup_batched_over_petsc": best["petsc"] / best["batched"],
               "per_repeat_ratios": [p / b for p, b in zip(times["petsc"], times["batched"])],
               "max_rel_diff_u": rel(u_b, u_p), "max_rel_diff_grad_f": rel(g_b, g_p),
               "auto_engine": layers["auto"].stats.last.engine}
        rows.append(row)
        print(f"{size:>6} {prob.output_size:>7} {row['solver']:>16} B={batch:<3} petsc {best['petsc']:8.3f}s batched "
              f"{best['batched']:8.3f}s speedup {row['speedup_batched_over_petsc']:5.2f} "
              f"diff u {row['max_rel_diff_u']:.1e} grad {row['max_rel_diff_grad_f']:.1e} auto {row['auto_engine']}",
              flush=True)
        for layer in layers.values():
            layer.close()
    return rows


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=3,
                                 quick="the small mesh, CG and GMRES at B = 32 only", quick_repeats=1)
    parser.add_argument("--sizes", type=comma_list(str), default=["small", "large"])
    parser.add_argument("--solvers", type=comma_list(str), default=["cg", "gmres", "cg-rtol"],
                        help="cg, gmres (capped at --k) and cg-rtol (CG + Jacobi to rtol 1e-8, no cap)")
    parser.add_argument("--k", type=int, default=200)
    parser.add_argument("--batches", type=comma_list(int), default=[2, 4, 8, 32],
                        help="batch sizes; all but the largest only for --small-batch-solvers")
    parser.add_argument("--small-batch-solvers", type=comma_list(str), default=["cg"])
    parser.add_argument("--threads", type=int, default=None)
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.solvers, args.batches = ["small"], ["cg", "gmres"], [32]
    if args.threads:
        torch.set_num_threads(args.threads)
    rng = np.random.default_rng(0)
    with bench_common.report(__file__, args.out, repeats=args.repeats, target_speedup=TARGET,
                             problem="poisson on lshape, control f, g = 1 + x*y; one call = B forward + B "
                                     "transposed solves", results=[]) as data:
        for size in args.sizes:
            data["results"] += bench(size, args, rng, data)
            data.save()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
