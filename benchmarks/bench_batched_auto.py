"""Benchmark: the rule of ``engine="auto"`` (``BatchedEngine.faster_than_petsc``) against both engines.

2D Poisson, P1 on a unit square of N x N cells (N = 16 ... 256: 289 to 66k unknowns, about 7 nonzeros
per row), the source f as control, B random sources. One timed call is
``u = layer(f=F); (u * W).sum().backward()``: B forward and B transposed solves, on the PETSc engine
(one KSP solve per sample) and on the batched engine (all samples at once), interleaved round by
round (``bench_common.interleaved``, every other round reversed) and reduced by the median. Solvers:
Richardson + Jacobi and CG + Jacobi capped at K = 20 and 200, and CG + Jacobi to rtol 1e-8 (each
column stopping at its own tolerance).

At every point the rule picks an engine from what it is given in a layer (B, the method, the cap
and the matrix's nonzeros); "auto" is the time of the engine it picks (the same measurement, not a
third run). Recorded per point: both times, their samples, auto / petsc, auto / best and batched /
petsc, the iterations, and the largest relative difference of u and dJ/df between the engines. The
acceptance is auto / min(petsc, batched) <= 1.2 at every point; the worst point is reported.

The time is kept to a few minutes by a budget on B x n (``--max-work``): the largest grids run the
small batches only (both engines' cost per column is flat in B at those sizes). The machine is
shared: the load is recorded before, during (after every round) and after the run.

Run::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_batched_auto.py
    .venv/bin/python benchmarks/bench_batched_auto.py --quick          # N = 16, 32; B = 2, 8; 1 repeat
"""
from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")   # before torch loads OpenMP

import functools  # noqa: E402
import time  # noqa: E402

from mpi4py import MPI  # noqa: E402  (before DOLFINx)
import dolfinx.mesh  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

import fempdl.forms  # noqa: E402
from fempdl.bridge_torch import SolveLayer  # noqa: E402
from fempdl.iterative import batched  # noqa: E402
from fempdl.ksp_adjoint import KSPOptions  # noqa: E402

import bench_common  # noqa: E402
from bench_common import comma_list  # noqa: E402

ACCEPT = 1.2
CONVERGED_RTOL = 1e-8
SOLVERS = ("richardson-20", "richardson-200", "cg-20", "cg-200", "cg-rtol")
STATISTIC = "median"


def options(solver: str, engine: str) -> KSPOptions:
    """``richardson-K`` / ``cg-K``: Jacobi-preconditioned, capped at K; ``cg-rtol``: CG + Jacobi to rtol 1e-8."""
    if solver == "cg-rtol":
        return KSPOptions.preset("cg", rtol=CONVERGED_RTOL, engine=engine)
    method, cap = solver.split("-")
    return KSPOptions(ksp_type=method, pc_type="jacobi", max_it=int(cap), engine=engine)


def run(layer, F, W, keep: dict) -> float:
    """One call (forward and adjoint); its wall time. The last outputs are kept for the comparison."""
    F.grad = None
    t0 = time.perf_counter()
    u = layer(f=F)
    (u * W).sum().backward()
    seconds = time.perf_counter() - t0
    keep["u"], keep["grad"] = u.detach().numpy(), F.grad.numpy().copy()
    return seconds


def rel(X, Y) -> float:
    return float(np.max(np.linalg.norm(X - Y, axis=1) / np.maximum(np.linalg.norm(Y, axis=1), 1e-300)))


def rule(batch: int, opts: KSPOptions, nnz: int) -> str:
    """The engine ``engine="auto"`` picks for this call (both directions' options, as the layer asks)."""
    fast = all(batched.BatchedEngine.faster_than_petsc(batch, o.ksp_type, options=o, nnz=nnz)
               for o in (opts, opts.adjoint_options))
    return "batched" if fast else "petsc"


def bench_size(N: int, args, rng, data: bench_common.Report) -> list[dict]:
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, N, N)
    prob = fempdl.forms.poisson.problem(msh, controls=("f",))
    n = prob.output_size
    batches = [b for b in args.batches if b * n <= args.max_work]
    rows = [{"N": N, "n": n, "B": b, "skipped": f"B x n = {b * n} over --max-work {args.max_work}"}
            for b in args.batches if b not in batches]
    if not batches:
        return rows
    F_all = rng.standard_normal((max(batches), prob.control_size("f")))
    W_all = torch.from_numpy(rng.standard_normal((max(batches), n)))
    for solver in args.solvers:
        layers = {e: SolveLayer(prob, options(solver, e)) for e in ("petsc", "batched")}
        nnz = layers["petsc"].system.constant_matrix().nnz          # the stored pattern, as the engine counts it
        kept = {e: {} for e in layers}
        for e, layer in layers.items():            # warm-up: forms, matrices, the engine's copy
            run(layer, torch.from_numpy(F_all[:min(batches)].copy()).requires_grad_(), W_all[:min(batches)], kept[e])
        for batch in batches:
            F = torch.from_numpy(F_all[:batch].copy()).requires_grad_()
            W = W_all[:batch]
            before = {e: layer.stats.total_iterations for e, layer in layers.items()}
            timings = bench_common.interleaved(
                {e: functools.partial(run, layers[e], F, W, kept[e]) for e in layers},
                repeats=args.repeats, warmup=0, alternate=True, statistic=STATISTIC, report=data)
            t = {e: timing.seconds for e, timing in timings.items()}
            choice = rule(batch, layers["petsc"].options, nnz)
            best = min(t.values())
            row = {"N": N, "n": n, "nnz": nnz, "solver": solver, "B": batch,
                   "K": None if solver == "cg-rtol" else int(solver.split("-")[1]),
                   "seconds": t, "samples": {e: list(timing.samples) for e, timing in timings.items()},
                   "auto_engine": choice, "auto_seconds": t[choice],
                   "auto_over_petsc": t[choice] / t["petsc"], "auto_over_best": t[choice] / best,
                   "batched_over_petsc": t["batched"] / t["petsc"],
                   "faster_engine": min(t, key=t.get),
                   "auto_engine_without_nnz": ("batched" if all(
                       batched.BatchedEngine.faster_than_petsc(batch, o.ksp_type)
                       for o in (layers["petsc"].options, layers["petsc"].options.adjoint_options)) else "petsc"),
                   "iterations_per_sample_fwd_plus_bwd": {
                       e: (layer.stats.total_iterations - before[e]) / (args.repeats * batch)
                       for e, layer in layers.items()},
                   "max_rel_diff_u": rel(kept["batched"]["u"], kept["petsc"]["u"]),
                   "max_rel_diff_grad_f": rel(kept["batched"]["grad"], kept["petsc"]["grad"])}
            rows.append(row)
            print(f"n={n:6d} {solver:>15} B={batch:<4d} petsc {t['petsc'] * 1e3:9.2f} ms  batched "
                  f"{t['batched'] * 1e3:9.2f} ms  auto={choice:<7} auto/best {row['auto_over_best']:4.2f}  "
                  f"diff u {row['max_rel_diff_u']:.0e}", flush=True)
        for layer in layers.values():
            layer.close()
    return rows


def summary(rows: list[dict]) -> dict:
    timed = [r for r in rows if "skipped" not in r]
    worst = max(timed, key=lambda r: r["auto_over_best"])
    keys = ("n", "solver", "B", "auto_engine", "faster_engine", "auto_over_best", "auto_over_petsc")
    wrong = [{k: r[k] for k in keys} for r in timed if r["auto_engine"] != r["faster_engine"]]
    return {"points": len(timed), "skipped": len(rows) - len(timed),
            "worst_auto_over_best": worst["auto_over_best"], "worst_point": {k: worst[k] for k in keys},
            "accepted": worst["auto_over_best"] <= ACCEPT,
            "points_where_auto_is_not_the_faster": wrong,
            "auto_over_best_without_nnz_worst": max(
                r["seconds"][r["auto_engine_without_nnz"]] / min(r["seconds"].values()) for r in timed)}


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=3,
                                 quick="N = 16 and 32, B = 2 and 8, all solvers", quick_repeats=1)
    parser.add_argument("--sizes", type=comma_list(int), default=[16, 32, 64, 128, 256],
                        help="cells per side N of the unit square (n = (N + 1)^2 unknowns)")
    parser.add_argument("--batches", type=comma_list(int), default=[2, 8, 32, 128])
    parser.add_argument("--solvers", type=comma_list(str), default=list(SOLVERS), help=", ".join(SOLVERS))
    parser.add_argument("--max-work", type=int, default=600_000,
                        help="largest B x n timed (default %(default)s: 66k unknowns at B <= 8)")
    args = parser.parse_args(argv)
    if args.quick:
        args.sizes, args.batches = [16, 32], [2, 8]
    unknown = sorted(set(args.solvers) - set(SOLVERS))
    if unknown:
        parser.error(f"--solvers: unknown {unknown}; choose from {list(SOLVERS)}")
    rng = np.random.default_rng(0)
    rule_constants = {"RICHARDSON_MIN_BATCH": batched.tuning.RICHARDSON_MIN_BATCH,
                      "AUTO_FULL_BATCH": batched.AUTO_FULL_BATCH,
                      "RICHARDSON_MIN_WORK": batched.RICHARDSON_MIN_WORK,
                      "CG_MIN_BATCH": batched.tuning.CG_MIN_BATCH, "CG_MIN_NONZEROS": batched.CG_MIN_NONZEROS}
    t0 = time.perf_counter()
    with bench_common.report(__file__, args.out, statistic=STATISTIC, repeats=args.repeats, accept=ACCEPT,
                             problem="poisson P1 on a unit square, control f, g = 0; one call = B forward + B "
                                     "transposed solves through SolveLayer",
                             rule=rule_constants, torch_threads=torch.get_num_threads(), results=[]) as data:
        for N in args.sizes:
            data["results"] += bench_size(N, args, rng, data)
            data["summary"] = summary(data["results"])
            data.save()
        data["seconds_total"] = time.perf_counter() - t0
        s = data["summary"]
        print(f"worst auto/best {s['worst_auto_over_best']:.2f} at {s['worst_point']} "
              f"({'accepted' if s['accepted'] else 'NOT accepted'}, limit {ACCEPT}); "
              f"{data['seconds_total']:.0f} s", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
