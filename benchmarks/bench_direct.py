"""SIMP topology optimisation through a direct-solve layer: time per Adam step, against an earlier revision.

The workload users run: 3D linear elasticity on a hexahedral box [0, 2] x [0, 1] x [0, 1]
(12 x 6 x 4 cells, Q1, 1365 DOFs) clamped at x = 0 and pulled down on the far
bottom edge; a DG0 density rho = sigmoid(theta) per cell, Young's modulus
E = 1e-3 + rho^3 (SIMP), passed to a ``SolveLayer(problem, "lu")`` as a matrix
control, one sample per call, either as one (n_cells,) tensor (shared) or as a
(1, n_cells) batch; loss = compliance f.u + 10 (mean(rho) - 0.4)^2, Adam (lr 0.05).

Each step factorises A for the forward solve; the adjoint A^T lam = f must not
factorise it again (the same matrix: one factorisation, MatSolveTranspose on it).
The script times ``--steps`` Adam steps (after ``--warmup``) in a worker process for
variant: ``--baseline`` (a git revision, checked out into a temporary worktree)
with the ``"lu"`` preset, and this checkout with ``"lu"`` and with ``"cholesky"``
(the problem declared symmetric), alternating ``--repeats`` times
(``bench_common.interleaved``) so that machine load hits them alike; the figure
is the ratio of the medians of the per-round median step times. Writes
``bench-results/bench_direct.json`` (``--out``) through ``bench_common.report``;
``--quick``: 30 steps, one round.

Run (from the repository root, on an idle machine)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_direct.py --baseline af7188c
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TARGET_SPEEDUP = 2.0


def workload(steps: int, warmup: int, batched: bool) -> dict:
    """Run the SIMP loop in this process (fempdl from sys.path); per-step seconds and the last compliance."""
    from mpi4py import MPI
    import dolfinx.fem
    import dolfinx.mesh
    import numpy as np
    import torch
    import ufl

    from fempdl import Problem, SolveLayer
    from fempdl.core import _dolfinx

    torch.set_num_threads(1)
    msh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [2, 1, 1]], [12, 6, 4],
                                  dolfinx.mesh.CellType.hexahedron)
    V = _dolfinx.function_space(msh, "Lagrange", 1, shape=(3,))
    E = dolfinx.fem.Function(_dolfinx.function_space(msh, "DG", 0))
    E.x.array[:] = 1.0
    nu = 0.3
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    u, v = ufl.TrialFunction(V), ufl.TestFunction(V)

    def eps(w):
        return ufl.sym(ufl.grad(w))
    a = ufl.inner(2 * mu * eps(u) + lmbda * ufl.tr(eps(u)) * ufl.Identity(3), eps(v)) * ufl.dx
    fdim = msh.topology.dim - 1
    edge = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 2.0) & (x[2] < 0.3))
    tags = dolfinx.mesh.meshtags(msh, fdim, edge, np.ones(len(edge), dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    load = dolfinx.fem.Constant(msh, np.array([0.0, 0.0, -1.0]))
    L = ufl.inner(load, v) * ds(1)
    clamp = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Function(V), clamp)
    # symmetric=True where this revision knows it (the Cholesky preset needs it); an older one runs "lu" only.
    symmetric = {"symmetric": True} if "symmetric" in Problem.__init__.__code__.co_varnames else {}
    problem = Problem(a, L, [bc], controls={"E": E}, **symmetric)
    layer = SolveLayer(problem, os.environ.get("BENCH_DIRECT_PRESET", "lu"))
    b = _dolfinx.create_vector(problem.L_form)
    _dolfinx.assemble_vector_into(b, problem.L_form, problem.a_form, problem.bcs)
    f = torch.from_numpy(b.getArray(readonly=True)[:problem.output_size].copy())
    theta = torch.zeros(problem.control_size("E"), dtype=torch.float64, requires_grad=True)
    optimizer = torch.optim.Adam([theta], lr=0.05)
    times = []
    for step in range(warmup + steps):
        t0 = time.perf_counter()
        optimizer.zero_grad()
        rho = torch.sigmoid(theta)
        young = 1e-3 + rho ** 3
        u_h = layer(E=young[None] if batched else young)
        compliance = (f * u_h).sum()
        loss = compliance + 10.0 * (rho.mean() - 0.4) ** 2
        loss.backward()
        optimizer.step()
        if step >= warmup:
            times.append(time.perf_counter() - t0)
    stats = layer.stats
    return {"step_s": times, "compliance": float(compliance), "dofs": problem.output_size,
            "cells": problem.control_size("E"), "setup_s": stats.setup_time, "solve_s": stats.solve_time,
            "assembly_s": stats.assembly_time, "forward_solves": stats.forward_solves,
            "backward_solves": stats.backward_solves}


def run_worker(tree: Path, args, batched: bool, preset: str) -> dict:
    env = {**os.environ, "PYTHONPATH": str(tree), "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1",
           "BENCH_DIRECT_PRESET": preset}
    command = [sys.executable, str(Path(__file__).resolve()), "--worker", "--steps", str(args.steps),
               "--warmup", str(args.warmup)] + (["--batched"] if batched else [])
    done = subprocess.run(command, env=env, cwd=tree, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"worker in {tree} failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def median_step(runs: list, tree: Path, args, batched: bool, preset: str):
    """One round of a variant: a worker run, appended to ``runs``; its median step time."""
    def run() -> float:
        runs.append(run_worker(tree, args, batched, preset))
        return statistics.median(runs[-1]["step_s"])
    return run


def main() -> int:
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import bench_common

    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=3, quick="30 steps", quick_repeats=1)
    parser.add_argument("--baseline", default=None, help="git revision to compare with (omit: this tree only)")
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--warmup", type=int, default=10)
    parser.add_argument("--batched", action="store_true", help="worker: pass the control as a (1, n) batch")
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        print(json.dumps(workload(args.steps, args.warmup, args.batched)))
        return 0
    if args.quick:
        args.steps = 30

    variants = {"current lu": (ROOT, "lu"), "current cholesky": (ROOT, "cholesky")}
    scratch = None
    if args.baseline:
        scratch = Path(tempfile.mkdtemp(prefix="fempdl-baseline-"))
        subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(scratch), args.baseline],
                       check=True)
        variants = {"baseline lu": (scratch, "lu"), **variants}
    with contextlib.ExitStack() as cleanup:
        report = cleanup.enter_context(bench_common.report(
            __file__, args.out, statistic="median", repeats=args.repeats,
            settings={"steps": args.steps, "warmup": args.warmup, "baseline": args.baseline,
                      "workload": __doc__.split("\n\n")[1]},
            target_speedup_min=TARGET_SPEEDUP, results={}))
        if scratch is not None:
            cleanup.callback(subprocess.run, ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(scratch)],
                             check=False)
        for layout in ("shared", "batched"):
            rounds = {name: [] for name in variants}
            steps = {name: median_step(rounds[name], tree, args, layout == "batched", preset)
                     for name, (tree, preset) in variants.items()}
            timings = bench_common.interleaved(steps, repeats=args.repeats, warmup=0, statistic="median")
            row = {}
            for name, runs in rounds.items():
                row[name] = {"median_step_s": timings[name].seconds, "round_medians_s": list(timings[name].samples),
                             "compliance": runs[-1]["compliance"], "dofs": runs[-1]["dofs"],
                             "setup_s_last_round": runs[-1]["setup_s"], "solve_s_last_round": runs[-1]["solve_s"],
                             "assembly_s_last_round": runs[-1]["assembly_s"]}
            if "baseline lu" in row:
                for name in ("current lu", "current cholesky"):
                    row[f"speedup {name}"] = row["baseline lu"]["median_step_s"] / row[name]["median_step_s"]
            report["results"][layout] = row
            print(layout, json.dumps({k: round(v["median_step_s"] * 1e3, 2) if isinstance(v, dict) else round(v, 2)
                                      for k, v in row.items()}), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
