"""Benchmark: saddle-point solvers for the Stokes and Oseen layers, forward and adjoint.

Setup: Taylor-Hood P2-P1 on two bundled meshes: the DFG channel
(``mesh.load("obstacle", h=0.05)``, parabolic inflow of peak 1.5, no-slip walls
and cylinder, do-nothing outlet) and the enclosed L-shape
(``mesh.load("lshape", h=0.05)``, no-slip everywhere: the pressure null space is
attached). Problems: Stokes (nu = 1) and one Oseen step (dt = 0.1, SUPG,
advecting velocity = the inflow profile in the channel, a rotation in the
L-shape) at nu in {1e-2, 1e-3}.

For each problem and solver, one layer call with the velocity control
``u_prev`` (Oseen) or ``f`` (Stokes) requiring grad, then backward of
sum(x * g) for a fixed random g; everything solved to rtol 1e-8. Recorded: the
forward and adjoint (backward) iteration counts, the wall time of the call,
failures, and for the adjoint the relative difference of the gradient from
the LU (MUMPS) gradient. Solvers:

* ``schur-lsc``: the ``"schur"`` preset (GMRES(50), full Schur fieldsplit,
  velocity LU, Schur complement by LSC with hypre); the adjoint runs on the
  assembled A^T (``adjoint_operator="auto"`` picks it for fieldsplit).
* ``schur-selfp``: the same with the "selfp" Schur approximation and Jacobi.
* ``schur-lsc-transpose``: ``"schur"`` with ``adjoint_operator="transpose"``
  (KSPSolveTranspose through a fieldsplit, which PETSc 3.18 cannot
  transpose): shows what the assembled adjoint avoids.
* ``lu``: MUMPS, for the reference gradient.

Each call (forward + backward, a fresh layer) runs ``--repeats`` times (default 1;
``bench_common.repeat_runs``, the fastest counts). Writes
``bench-results/bench_flow.json`` (``--out``) through ``bench_common.report`` and
prints a table. Run: ``python benchmarks/bench_flow.py`` (about a minute);
``--quick``: h = 0.1.
"""
from __future__ import annotations

import dataclasses
import functools
import sys
import time

from mpi4py import MPI
import numpy as np
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions, SolverFailedError

import bench_common

HEIGHT = 0.41


def inflow(x):
    return np.stack([6.0 * x[1] * (HEIGHT - x[1]) / HEIGHT ** 2, 0.0 * x[0]])


def rotation(x):
    return np.stack([-x[1], x[0]])


def solvers() -> dict:
    schur = KSPOptions.preset("schur", rtol=1e-8)
    selfp = {**schur.petsc_options, "pc_fieldsplit_schur_precondition": "selfp", "fieldsplit_p_pc_type": "jacobi"}
    del selfp["fieldsplit_p_lsc_pc_type"]
    return {"schur-lsc": schur,
            "schur-selfp": dataclasses.replace(schur, petsc_options=selfp),
            "schur-lsc-transpose": dataclasses.replace(schur, adjoint_operator="transpose"),
            "lu": KSPOptions.preset("lu")}


def problems(h: float) -> dict:
    channel = mesh.load("obstacle", MPI.COMM_SELF, h=h)
    lshape = mesh.load("lshape", MPI.COMM_SELF, h=h)
    walls = {"inlet": inflow, "walls": 0.0, "obstacle": 0.0}
    out = {"stokes-channel": (forms.stokes.problem(channel, velocity=walls), "f", None),
           "stokes-enclosed": (forms.stokes.problem(lshape, f=(1.0, 0.5)), "f", None)}
    for nu in (1e-2, 1e-3):
        out[f"oseen-channel-nu{nu:g}"] = (forms.oseen.problem(channel, controls=("w", "u_prev"), nu=nu, dt=0.1,
                                                               velocity=walls), "u_prev", inflow)
        out[f"oseen-enclosed-nu{nu:g}"] = (forms.oseen.problem(lshape, controls=("w", "u_prev"), nu=nu, dt=0.1),
                                           "u_prev", rotation)
    return out


def call(prob, control: str, advecting, options: KSPOptions, g: torch.Tensor) -> dict:
    layer = SolveLayer(prob, options)
    if advecting is None:
        m = torch.as_tensor(prob.interpolate(lambda x: np.stack([np.sin(3 * x[1]), np.cos(2 * x[0])]), control))
        inputs = {}
    else:
        m = torch.as_tensor(prob.interpolate(advecting, control))
        inputs = {"w": m.clone()}
    m = m.clone().requires_grad_()
    t0 = time.perf_counter()
    try:
        (layer(**inputs, **{control: m}) * g).sum().backward()
    except SolverFailedError as err:
        return {"failed": str(err).split(";")[0], "forward_iterations": layer.stats.forward_iterations,
                "backward_iterations": layer.stats.backward_iterations}
    return {"seconds": time.perf_counter() - t0, "forward_iterations": layer.stats.forward_iterations,
            "backward_iterations": layer.stats.backward_iterations, "grad": m.grad.numpy().copy()}


def main() -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=1, quick="h = 0.1")
    parser.add_argument("--h", type=float, default=None, help="mesh size of both meshes (default 0.05)")
    args = parser.parse_args()
    args.h = args.h or (0.1 if args.quick else 0.05)
    with bench_common.report(__file__, args.out, repeats=args.repeats, h=args.h, rtol=1e-8) as report:
        report["rows"] = measure(args)
    return 0


def measure(args) -> list:
    rows = []
    for name, (prob, control, advecting) in problems(args.h).items():
        g = torch.from_numpy(np.random.default_rng(0).standard_normal(prob.output_size))
        results = {label: bench_common.repeat_runs(functools.partial(call, prob, control, advecting, opts, g),
                                                   "seconds", repeats=args.repeats)
                   for label, opts in solvers().items()}
        reference = results["lu"].get("grad")
        for label, r in results.items():
            grad = r.pop("grad", None)
            r.pop("seconds_samples", None)
            if grad is not None and reference is not None:
                r["grad_error_vs_lu"] = float(np.linalg.norm(grad - reference) / np.linalg.norm(reference))
            rows.append({"problem": name, "dofs": prob.output_size, "enclosed": prob.enclosed, "solver": label, **r})
            print(f"{name:24s} {prob.output_size:6d} {label:20s} fwd {r['forward_iterations']:6d} "
                  f"adj {r['backward_iterations']:6d} "
                  + (f"grad err {r['grad_error_vs_lu']:.1e} " if "grad_error_vs_lu" in r else "")
                  + (f"{r['seconds']:.2f} s" if "seconds" in r else f"FAILED: {r['failed']}"), flush=True)
    return rows


if __name__ == "__main__":
    sys.exit(main())
