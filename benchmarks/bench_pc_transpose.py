"""Benchmark: which preconditioners PETSc can transpose, on the stack this runs on.

The adjoint of a layer solves A^T y = c. ``KSPOptions(adjoint_operator=...)``
does it either by KSPSolveTranspose on A (``"transpose"``: the preconditioner's
transpose is applied) or by a normal KSPSolve on an explicitly assembled A^T
(``"assembled"``). PETSc 3.18 (Debian) has no transpose of the Schur fieldsplit
and a broken one for hypre; this script measures, for every preconditioner the
PETSc build offers, whether KSPSolveTranspose gives the adjoint:

* ``transpose_error``: ||y - y_lu|| / ||y_lu|| against the LU (MUMPS) solution
  of A^T y = c;
* ``dot_product_error``: |<x, c> - <b, y>| / |<x, c>| with A x = b solved by the
  same options (the adjoint dot-product test);
* forward, transposed and assembled-A^T iteration counts and PETSc's reasons.

Every solve runs GMRES(50) to rtol 1e-10 (the fieldsplit ones at most 10,000
iterations, the others 1000).
Problems (P2-P1 Taylor-Hood or P1 vector, assembled through fempdl):
``oseen-channel`` (DFG channel, h = 0.05, nu = 1e-3, SUPG), ``oseen-lshape``
(L-shape h = 0.1, no-slip outer boundary, do-nothing reentrant edges, nu = 0.05)
and ``burgers-lshape`` (vector P1 Burgers step, nu = 1e-2).

Each (problem, preconditioner) runs in its own process: a PETSc error inside
KSPSolveTranspose (a preconditioner without a transpose) can leave mpi4py 4
deadlocked when PETSc objects are freed afterwards.

Writes ``bench-results/bench_pc_transpose_<stack>.json`` (``--out``) through
``bench_common.report`` (nothing is timed: iteration counts and errors). ``--quick``:
``burgers-lshape`` only.
Run: ``python benchmarks/bench_pc_transpose.py`` (a minute or two).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys

from mpi4py import MPI  # before DOLFINx (PyPI's DOLFINx needs the MPI library loaded)
import numpy as np
from petsc4py import PETSc

from fempdl import forms, mesh
from fempdl.core import _dolfinx, matrices
from fempdl.ksp_adjoint import CappedSolver, KSPOptions, SolverFailedError

import bench_common

RTOL = 1e-10
HEIGHT = 0.41


def inflow(x):
    return np.stack([6.0 * x[1] * (HEIGHT - x[1]) / HEIGHT ** 2, 0.0 * x[0]])


def rotation(x):
    return np.stack([-x[1], x[0]])


def problems() -> dict:
    channel = mesh.load("obstacle", MPI.COMM_SELF, h=0.05)
    lshape = mesh.load("lshape", MPI.COMM_SELF, h=0.1)
    walls = {"inlet": inflow, "walls": 0.0, "obstacle": 0.0}
    return {
        "oseen-channel": forms.oseen.problem(channel, controls=(), nu=1e-3, dt=0.1, w=inflow, velocity=walls),
        "oseen-lshape": forms.oseen.problem(lshape, controls=(), nu=0.05, dt=0.2, w=rotation,
                                            velocity={"outer": 0.0}),
        "burgers-lshape": forms.burgers.problem(lshape, controls=(), nu=1e-2, dt=0.1, w=rotation),
    }


def gmres(pc_type: str, **petsc_options) -> KSPOptions:
    return KSPOptions(ksp_type="gmres", pc_type=pc_type, gmres_restart=50, max_it=1000, rtol=RTOL,
                      petsc_options=petsc_options)


def preconditioners(saddle_point: bool) -> dict:
    """Name -> options, for the preconditioners this PETSc build has."""
    if saddle_point:
        schur = KSPOptions.preset("schur", rtol=RTOL)
        lsc = {k: v for k, v in schur.petsc_options.items() if not k.startswith("fieldsplit_p_lsc_")}
        inner = "hypre" if schur.petsc_options["fieldsplit_p_lsc_pc_type"] == "hypre" else "mumps"
        selfp = {**lsc, "pc_fieldsplit_schur_precondition": "selfp", "fieldsplit_p_pc_type": "jacobi"}
        return {f"schur-lsc-{inner} (preset)": schur,
                "schur-selfp-jacobi": dataclasses.replace(schur, petsc_options=selfp)}
    out = {"jacobi": gmres("jacobi"), "ilu": gmres("ilu"), "sor": gmres("sor"), "gamg": gmres("gamg")}
    if PETSc.Sys.hasExternalPackage("hypre"):
        out["hypre"] = gmres("hypre")
    return out


def assembled_system(prob):
    A = matrices.create_matrix(prob.a_form)
    matrices.assemble_matrix_into(A, prob.a_form, prob.bcs)
    return A


def solve(A, options: KSPOptions, fields, rhs: PETSc.Vec, transpose: bool) -> tuple[np.ndarray, dict]:
    """Solve with ``options``; a PETSc error (e.g. a PC without a transpose) propagates, and
    the PETSc objects are then left alone (destroying them can deadlock, see above)."""
    out = rhs.duplicate()
    solver = CappedSolver(A, options, fields=fields)
    try:
        stats = solver.solve_transpose(rhs, out) if transpose else solver.solve(rhs, out)
        info = {"iterations": stats.iterations, "reason": stats.reason_name}
    except SolverFailedError as err:
        info = {"iterations": err.stats.iterations, "reason": err.stats.reason_name, "failed": True}
    values = out.getArray().copy()
    solver.destroy()
    out.destroy()
    return values, info


def measure(prob, options: KSPOptions) -> dict:
    A = assembled_system(prob)
    fields = prob.fields or None
    rng = np.random.default_rng(0)
    b, c = A.createVecLeft(), A.createVecLeft()
    b.setArray(rng.standard_normal(b.getLocalSize()))
    c.setArray(rng.standard_normal(c.getLocalSize()))
    lu = KSPOptions.preset("lu")
    y_lu, _ = solve(A, lu, fields, c, transpose=True)
    x, forward = solve(A, options, fields, b, transpose=False)
    y_asm, assembled = solve(A, dataclasses.replace(options, adjoint_operator="assembled"), fields, c, transpose=True)
    row = {"forward": forward, "assembled": assembled,
           "assembled_error": float(np.linalg.norm(y_asm - y_lu) / np.linalg.norm(y_lu))}
    try:                                      # last: a PETSc error here ends the worker
        y, row["transpose"] = solve(A, dataclasses.replace(options, adjoint_operator="transpose"), fields, c,
                                    transpose=True)
    except PETSc.Error as err:
        row["transpose"] = {"iterations": -1, "reason": f"PETSc error {err.ierr}", "failed": True}
        row["transpose_error"] = row["dot_product_error"] = None
        return row
    xc, by = float(x @ c.getArray()), float(b.getArray() @ y)
    row["transpose_error"] = float(np.linalg.norm(y - y_lu) / np.linalg.norm(y_lu))
    row["dot_product_error"] = abs(xc - by) / abs(xc)
    for v in (b, c):
        v.destroy()
    A.destroy()
    return row


SADDLE_POINT = {"oseen-channel": True, "oseen-lshape": True, "burgers-lshape": False}


def worker(problem: str, label: str) -> None:
    prob = problems()[problem]
    row = {"problem": problem, "dofs": prob.output_size, "preconditioner": label,
           **measure(prob, preconditioners(SADDLE_POINT[problem])[label])}
    print("RESULT " + json.dumps(row), flush=True)
    os._exit(0)   # skip finalisation: after a PETSc error it can deadlock (see the docstring)


def run_worker(problem: str, label: str) -> dict:
    command = [sys.executable, __file__, "--worker", problem, label]
    try:
        done = subprocess.run(command, capture_output=True, text=True, timeout=600)
    except subprocess.TimeoutExpired:
        return {"problem": problem, "preconditioner": label, "error": "timed out after 600 s"}
    for line in done.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    return {"problem": problem, "preconditioner": label,
            "error": f"exit {done.returncode}: " + " | ".join(done.stderr.strip().splitlines()[-3:])}


def main() -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=None, quick="burgers-lshape only",
                                 out_suffix=f"_{_dolfinx.STACK}")
    parser.add_argument("--worker", nargs=2, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        worker(*args.worker)
        return 0
    names = ["burgers-lshape"] if args.quick else list(SADDLE_POINT)
    with bench_common.report(__file__, args.out, statistic=None, repeats=None, rtol=RTOL) as report:
        report["rows"] = measure_all(names)
    return 0


def measure_all(names: list) -> list:
    rows = []
    for name in names:
        saddle_point = SADDLE_POINT[name]
        for label in preconditioners(saddle_point):
            row = run_worker(name, label)
            rows.append(row)
            if "error" in row:
                print(f"{name:16s} {label:22s} {row['error']}", flush=True)
                continue
            errors = (f"err {row['transpose_error']:.1e} dot {row['dot_product_error']:.1e}"
                      if row["transpose_error"] is not None else "")
            print(f"{name:16s} {label:22s} fwd {row['forward']['iterations']:5d} "
                  f"transpose {row['transpose']['iterations']:5d} {row['transpose']['reason']:22s} {errors} | "
                  f"assembled {row['assembled']['iterations']:5d} err {row['assembled_error']:.1e}", flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
