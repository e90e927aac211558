"""Benchmark: the same layer and scenes on both supported stacks.

Debian bookworm's DOLFINx 0.5.2 / PETSc 3.18 / Python 3.11 (``.venv``) against
DOLFINx 0.11 / PETSc 3.25 / Python 3.12 from PyPI (``.venv-pypi``). The driver
runs this script once in each venv (``--worker``), one after the other, and
writes both records and the ratios current / debian (below 1: the PyPI stack
is faster). Torch runs on one thread in both.

Measured in each venv:

* ``import``: seconds to import fempdl (DOLFINx, PETSc, torch) in a fresh process.
* ``layer``: the Poisson layer of docs/stacks.md on the L-shape at h = 0.02 (8.9k DOFs),
  batch 16, forward + backward (sum of squares), median of ``--repeats`` calls
  after one warm-up call (``bench_common.timed``), in ms per sample, for the ``jacobi`` preset capped at
  K = 100 (the batched torch engine), ``cg`` to rtol 1e-8 (PETSc, one KSP solve
  per sample) and ``lu`` (MUMPS); also the final values' digest, to show the
  stacks compute the same numbers.
* ``solve_columns``: 32 right-hand sides through a MUMPS LU of the same
  matrix, :func:`solve_columns` (one KSPMatSolve where petsc4py >= 3.19 has it)
  against one KSPSolve per column, ms (median of 5).
* ``scenes``: ``fempdl run SCENE --k 8 --epochs E --no-baseline --threads 1``
  for ``heat-emulator-2d`` and ``burgers-emulator``: wall seconds of the
  training (from metrics.json), of the whole command, and the final
  validation metric.

Writes ``bench-results/bench_stacks.json`` (``--out``) through ``bench_common.report``;
``--quick``: 1 epoch per scene, 2 repeats.
Run: ``python benchmarks/bench_stacks.py`` from either venv (a few minutes;
``make setup`` and ``make setup STACK=pypi`` first).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mpi4py import MPI  # before DOLFINx (PyPI's DOLFINx needs the MPI library loaded)
import numpy as np
import torch
from petsc4py import PETSc

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.core import matrices
from fempdl.ksp_adjoint import KSPOptions

import bench_common
from bench_common import machine_info, timed

ROOT = Path(__file__).resolve().parent.parent
VENVS = {"debian": ROOT / ".venv", "current": ROOT / ".venv-pypi"}
SCENES = ("heat-emulator-2d", "burgers-emulator")
STATISTIC = "median"


# ---------------------------------------------------------------- worker (inside one venv)
def layer_timings(repeats: int) -> dict:
    prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.02), controls=("f", "kappa"))
    batch = 16
    f = torch.as_tensor(np.random.default_rng(0).standard_normal((batch, prob.control_size("f"))))
    kappa = torch.ones(prob.control_size("kappa"), dtype=torch.float64)
    out = {"dofs": prob.output_size, "batch": batch}
    for name, options in {"jacobi_k100": KSPOptions.preset("jacobi", max_it=100),
                          "cg_rtol1e-8": KSPOptions.preset("cg", rtol=1e-8),
                          "lu": KSPOptions.preset("lu")}.items():
        layer = SolveLayer(prob, options)
        last = {}

        def call(layer=layer, last=last) -> float:
            last["f"] = fr = f.clone().requires_grad_()
            t0 = time.perf_counter()
            last["u"] = u = layer(f=fr, kappa=kappa)
            u.square().sum().backward()
            return time.perf_counter() - t0

        seconds = timed(call, repeats=repeats, statistic=STATISTIC).seconds
        u, fr = last["u"], last["f"]
        out[name] = {"ms_per_sample": 1e3 * seconds / batch,
                     "u_norm": float(u.detach().norm()), "grad_norm": float(fr.grad.norm()),
                     "iterations": layer.stats.forward_iterations + layer.stats.backward_iterations,
                     "engines": dict(layer.stats.solves_by_engine)}
    return out


def solve_columns(ksp: PETSc.KSP, B: np.ndarray) -> np.ndarray:
    """Solve A X = B for every column of B with ``ksp`` (its operator A set up).

    B is (owned rows, k), this rank's rows in the operator's row layout; returns
    X of the same shape. Where petsc4py has ``KSP.matSolve`` (PETSc >= 3.19)
    this is one KSPMatSolve: a direct solver then applies its factors to all
    columns at once (MatMatSolve). Otherwise, one KSPSolve per column. Krylov
    methods iterate each column either way (PETSc's KSPMatSolve loops them
    unless the KSP is a block method).
    """
    B = np.asarray(B, dtype=PETSc.ScalarType)
    if B.ndim != 2:
        raise ValueError(f"B must be (owned rows, columns), got shape {B.shape}")
    A = ksp.getOperators()[0]
    (n_local, n_global), _ = A.getSizes()
    if B.shape[0] != n_local:
        raise ValueError(f"B must have the operator's {n_local} owned rows on this rank, got {B.shape[0]}")
    k = B.shape[1]
    comm = A.getComm()
    if hasattr(ksp, "matSolve") and k > 0:
        # Dense PETSc matrices store their local rows column by column (Fortran order).
        rhs = PETSc.Mat().createDense(((n_local, n_global), (PETSc.DECIDE, k)),
                                      array=np.asfortranarray(B).ravel(order="F"), comm=comm)
        sol = PETSc.Mat().createDense(((n_local, n_global), (PETSc.DECIDE, k)), comm=comm)
        try:
            ksp.matSolve(rhs, sol)
            return sol.getDenseArray(readonly=True).copy(order="C")
        finally:
            rhs.destroy()
            sol.destroy()
    X = np.empty_like(B)
    b, x = A.createVecs()
    try:
        for j in range(k):
            b.getArray()[:] = B[:, j]
            ksp.solve(b, x)
            X[:, j] = x.getArray(readonly=True)
    finally:
        b.destroy()
        x.destroy()
    return X


def solve_columns_timings() -> dict:
    prob = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.01), controls=("f",))
    A = matrices.create_matrix(prob.a_form)
    matrices.assemble_matrix_into(A, prob.a_form, prob.bcs)
    ksp = PETSc.KSP().create(MPI.COMM_SELF)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    ksp.setUp()
    B = np.random.default_rng(0).standard_normal((A.getLocalSize()[0], 32))
    b, x = A.createVecs()

    def loop():
        X = np.empty_like(B)
        for j in range(B.shape[1]):
            b.getArray()[:] = B[:, j]
            ksp.solve(b, x)
            X[:, j] = x.getArray()
        return X

    def ms(fn) -> float:
        return 1e3 * timed(fn, repeats=5, statistic=STATISTIC).seconds

    together, one_by_one = ms(lambda: solve_columns(ksp, B)), ms(loop)
    difference = float(np.abs(solve_columns(ksp, B) - loop()).max())
    for obj in (b, x, ksp, A):
        obj.destroy()
    return {"dofs": int(B.shape[0]), "columns": int(B.shape[1]), "mat_solve": hasattr(ksp, "matSolve"),
            "solve_columns_ms": together, "column_loop_ms": one_by_one, "max_difference": difference}


def scene_timings(epochs: int) -> dict:
    out = {}
    for scene in SCENES:
        with tempfile.TemporaryDirectory() as tmp:
            command = [str(Path(sys.executable).parent / "fempdl"), "run", scene, "--k", "8", "--epochs", str(epochs),
                       "--no-baseline", "--no-progress", "--threads", "1", "--out", tmp]
            t0 = time.perf_counter()
            done = subprocess.run(command, capture_output=True, text=True)
            seconds = time.perf_counter() - t0
            if done.returncode != 0:
                raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-2000:]}")
            rows = json.loads(next(Path(tmp).rglob("metrics.json")).read_text())
        out[scene] = {"epochs": epochs, "train_wall_seconds": rows[-1]["wall_time"], "command_seconds": seconds,
                      "final_val_metric": rows[-1]["val_metric"], "total_iterations": rows[-1]["total_iterations"]}
    return out


def import_seconds() -> float:
    code = "import time; t0 = time.perf_counter(); import fempdl; print(time.perf_counter() - t0)"
    return timed(lambda: float(subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                                              check=True).stdout),
                 repeats=3, warmup=0, statistic=STATISTIC).seconds


def worker(args) -> dict:
    torch.set_num_threads(1)
    return {"machine": machine_info(), "import_seconds": import_seconds(), "layer": layer_timings(args.repeats),
            "solve_columns": solve_columns_timings(), "scenes": scene_timings(args.epochs)}


# ---------------------------------------------------------------- driver
def ratios(debian: dict, current: dict) -> dict:
    out = {"import": current["import_seconds"] / debian["import_seconds"]}
    for name, row in debian["layer"].items():
        if isinstance(row, dict):
            out[f"layer_{name}"] = current["layer"][name]["ms_per_sample"] / row["ms_per_sample"]
    for scene, row in debian["scenes"].items():
        out[f"scene_{scene}"] = current["scenes"][scene]["train_wall_seconds"] / row["train_wall_seconds"]
    out["lu_32_columns"] = current["solve_columns"]["solve_columns_ms"] / debian["solve_columns"]["solve_columns_ms"]
    return out


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=5, quick_repeats=2,
                                 quick="1 epoch per scene")
    parser.add_argument("--epochs", type=int, default=None, help="epochs per scene (default 5)")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    args.epochs = args.epochs or (1 if args.quick else 5)
    if args.worker:
        args.worker.write_text(json.dumps(worker(args)))
        return 0
    missing = [str(v) for v in VENVS.values() if not (v / "bin" / "python").exists()]
    if missing:
        parser.error(f"missing venv(s) {missing}; run `make setup` and `make setup STACK=pypi` first")
    with bench_common.report(__file__, args.out, statistic=STATISTIC, repeats=args.repeats,
                             settings={"epochs": args.epochs}) as report:
        report["stacks"] = results = run_stacks(args)
        report["ratio_current_over_debian"] = ratios(results["debian"], results["current"])
    for key, value in report["ratio_current_over_debian"].items():
        print(f"{key:32s} {value:6.2f}")
    return 0


def run_stacks(args) -> dict:
    results = {}
    env = {**os.environ, "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    with tempfile.TemporaryDirectory() as tmp:
        for stack, venv in VENVS.items():
            path = Path(tmp) / f"{stack}.json"
            command = [str(venv / "bin" / "python"), __file__, "--worker", str(path),
                       "--repeats", str(args.repeats), "--epochs", str(args.epochs)]
            print(f"[bench_stacks] {stack}: {' '.join(command)}", flush=True)
            subprocess.run(command, env=env, check=True)
            results[stack] = json.loads(path.read_text())
    return results


if __name__ == "__main__":
    sys.exit(main())
