"""Batched rollouts against separate calls: one Rollout call with B initial states against B calls with one.

The problems, on the unit square (P1, u = 0 on the boundary, dt = 0.01, ``--steps`` backward-Euler steps,
``--n`` cells per side: 9,409 DOFs by default), from B initial states u_0,i = (1 + 0.1 i) 2 sin(pi x) sin(pi y)
under one source f = 4 + 2 cos(3x) y shared by the batch, loss J = sum_i |u_N,i|^2 (the sum of squares of
the final states' DOF values), gradient dJ/df:

* ``heat``: linear heat (u - u_k) / dt - div(grad u) = f, ``forms.heat`` in a
  ``SolveLayer(problem, "lu")`` (MUMPS);
* ``nonlinear``: nonlinear heat (u - u_k) / dt - div((1 + u^2) grad u) = f,
  ``forms.nonlinear_diffusion`` in a ``NonlinearSolveLayer`` (SNES newtonls, basic line search, rtol 1e-10,
  atol 1e-12, MUMPS LU at every Newton step), as in ``benchmarks/bench_rollout.py``.

Each a ``Rollout(layer, "u0")`` (no schedule: one node). The sides, for each B in ``--batch``:

* ``batched``: one rollout call with the states (B, n);
* ``separate``: B rollout calls with a state (n,) each, each call's loss backpropagated on its own
  (f's gradient accumulates to the batched one).

Both are timed for the forward alone (under ``torch.no_grad()``) and for forward + gradient
(``loss.backward()``): the minimum of ``--repeats`` runs, alternated between the sides
(``bench_common.interleaved``), after a warm-up
of ``--warmup-steps`` steps. ``ratio`` is batched / separate (below 1: the batch pays). The final states
and dJ/df of the two must agree to 1e-10 relative, else the script exits non-zero. ``petsc_counts`` are
PETSc's event counts of one forward + gradient run of each side, taken after the timings with PETSc's
logging on (it stays off while timing): ``factorisations`` (MatLUFactorNum), ``solves`` (MatSolve: one
right-hand side), ``transposed_solves`` (MatSolveTranspose) and ``multi_rhs_solves`` (MatMatSolve: all
columns of a batch at once); so whether a batch factors once or per sample, forward and adjoint.
Each problem runs in a fresh process with OMP_NUM_THREADS=1. Writes
``bench-results/bench_rollout_batch.json`` (``--out``) through ``bench_common.report``.

Run (from the repository root, on an idle machine; either stack)::

    .venv-pypi/bin/python benchmarks/bench_rollout_batch.py
    .venv/bin/python benchmarks/bench_rollout_batch.py --out bench-results/bench_rollout_batch_debian.json

A smoke run: ``... --quick --out /tmp/bench_rollout_batch.json``.
"""
from __future__ import annotations

import os

# Before anything loads an OpenMP runtime (torch, the BLAS): one thread, as bench_rollout's sides run, and
# no spinning between parallel regions on a shared machine.
os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import json
import resource
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI  # noqa: F401  (the PyPI stack needs MPI loaded before dolfinx)

RTOL, ATOL, DT = 1e-10, 1e-12, 0.01
TOLERANCE = 1e-10            # batched against separate: final states and dJ/df, relative
PROBLEMS = ("heat", "nonlinear")
# PETSc's event names (at most 16 characters: "MatSolveTranspos" is MatSolveTranspose) -> the key reported.
EVENTS = {"MatLUFactorNum": "factorisations", "MatSolve": "solves", "MatSolveTranspos": "transposed_solves",
          "MatMatSolve": "multi_rhs_solves"}
ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------ the problems
def build(name: str, n: int):
    """The rollout of problem ``name`` on an n x n unit square, its step layer, u_0 and f (owned DOFs)."""
    import dolfinx.mesh
    import numpy as np

    from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, SolveLayer, forms

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    if name == "heat":
        layer = SolveLayer(forms.heat.problem(msh, controls=("u0", "f"), dt=DT), "lu")
    else:
        problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=1.0, dt=DT)
        layer = NonlinearSolveLayer(problem, NewtonOptions(rtol=RTOL, atol=ATOL, snes_type="newtonls",
                                                           linesearch="basic", ksp="lu"))
    x = layer.problem.dof_coordinates()
    u0 = 2 * np.sin(np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1])
    f = 4 + 2 * np.cos(3 * x[:, 0]) * x[:, 1]
    return Rollout(layer, "u0"), layer, u0, f


# ------------------------------------------------------------------ the two sides
# Each returns the final states (B, n) and dJ/df (None for the forward alone).
def batched(rollout, U0, f, steps: int, gradient: bool):
    import torch

    source = torch.tensor(f, requires_grad=gradient)
    with torch.set_grad_enabled(gradient):
        final = rollout(U0, steps, f=source, outputs=[steps])[:, -1]
        if gradient:
            final.square().sum().backward()
    return final.detach().numpy(), source.grad.numpy().copy() if gradient else None


def separate(rollout, U0, f, steps: int, gradient: bool):
    import numpy as np
    import torch

    source = torch.tensor(f, requires_grad=gradient)
    finals = []
    with torch.set_grad_enabled(gradient):
        for u0 in U0:
            final = rollout(u0, steps, f=source, outputs=[steps])[-1]
            if gradient:            # each call's own backward, as B independent users would run it
                final.square().sum().backward()
            finals.append(final.detach().numpy())
    return np.stack(finals), source.grad.numpy().copy() if gradient else None


SIDES = {"batched": batched, "separate": separate}
MODES = {"forward": False, "forward_gradient": True}


def rel_diff(a, b) -> float:
    import numpy as np

    return float(np.abs(a - b).max() / np.abs(b).max())


# ------------------------------------------------------------------ one problem, in its own process
def run_problem(args) -> dict:
    import numpy as np
    import torch

    from bench_common import interleaved

    rollout, layer, u0, f = build(args.problem, args.n)
    rows = []
    for B in args.batch:
        U0 = torch.tensor(np.stack([(1 + 0.1 * i) * u0 for i in range(B)]))
        for side in SIDES:             # the warm-up: every code path once, short
            for gradient in MODES.values():
                SIDES[side](rollout, U0, f, args.warmup_steps, gradient)
        results = {}

        def measurement(side: str, mode: str, results: dict = results, U0=U0):
            def run() -> None:
                results[side, mode] = SIDES[side](rollout, U0, f, args.steps, MODES[mode])
            return run

        # Alternated: a change in the machine's load hits both sides alike.
        times = interleaved({(side, mode): measurement(side, mode) for mode in MODES for side in SIDES},
                            repeats=args.repeats, warmup=0)
        row = {"batch": B}
        for mode in MODES:
            batched_s, separate_s = times["batched", mode].seconds, times["separate", mode].seconds
            row[mode] = {"batched_s": batched_s, "separate_s": separate_s, "ratio": batched_s / separate_s}
        row["final_rel_diff"] = max(rel_diff(results["batched", mode][0], results["separate", mode][0])
                                    for mode in MODES)
        row["forward_alone_rel_diff"] = rel_diff(results["batched", "forward"][0],
                                                 results["batched", "forward_gradient"][0])
        row["grad_rel_diff"] = rel_diff(results["batched", "forward_gradient"][1],
                                        results["separate", "forward_gradient"][1])
        if max(row["final_rel_diff"], row["forward_alone_rel_diff"], row["grad_rel_diff"]) > TOLERANCE:
            raise SystemExit(f"{args.problem}, B = {B}: batched and separate disagree: {row}")
        rows.append(row)
        print(json.dumps(row), file=sys.stderr, flush=True)
    counts = count_events(args, rollout, layer, u0, f)
    for row in rows:
        row["petsc_counts"] = counts[row["batch"]]
    return {"dofs": len(u0), "rows": rows,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def count_events(args, rollout, layer, u0, f) -> dict:
    """B -> side -> PETSc's event counts (EVENTS) and the layer's solves in one forward + gradient run.
    Run after the timings: PETSc's logging, once on, stays on for the process."""
    import numpy as np
    import torch
    from petsc4py import PETSc

    PETSc.Log.begin()
    stats = layer.system.stats
    events = {name: PETSc.Log.Event(name) for name in EVENTS}

    def snapshot():
        out = {key: events[name].getPerfInfo()["count"] for name, key in EVENTS.items()}
        out["layer_forward_solves"], out["layer_backward_solves"] = stats.forward_solves, stats.backward_solves
        if hasattr(stats, "newton_steps"):
            out["newton_steps"] = stats.newton_steps
        return out

    counts = {}
    for B in args.batch:
        U0 = torch.tensor(np.stack([(1 + 0.1 * i) * u0 for i in range(B)]))
        counts[B] = {}
        for side, run in SIDES.items():
            before = snapshot()
            run(rollout, U0, f, args.steps, True)
            after = snapshot()
            counts[B][side] = {key: after[key] - before[key] for key in after}
    return counts


# ------------------------------------------------------------------ the driver
def run_worker(problem: str, args) -> dict:
    cmd = [sys.executable, __file__, "--problem", problem, "--n", str(args.n), "--steps", str(args.steps),
           "--repeats", str(args.repeats), "--warmup-steps", str(args.warmup_steps),
           "--batch", *map(str, args.batch)]
    out = subprocess.run(cmd, stdout=subprocess.PIPE, text=True)      # its stderr (progress) goes through
    if out.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed (exit {out.returncode})")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    import bench_common

    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=3, quick_repeats=1,
                                 quick="n = 8, B = 1 and 3, 5 steps")
    parser.add_argument("--problem", choices=PROBLEMS, help="run one problem here (the driver's worker)")
    parser.add_argument("--problems", nargs="*", choices=PROBLEMS, default=list(PROBLEMS))
    parser.add_argument("--n", type=int, default=None, help="cells per side (default 96; P1 DOFs: (n+1)^2: 9,409)")
    parser.add_argument("--batch", type=int, nargs="*", default=None, help="batch sizes B (default 1 4 16)")
    parser.add_argument("--steps", type=int, default=None, help="time steps (default 20)")
    parser.add_argument("--warmup-steps", type=int, default=2, help="steps of the warm-up runs")
    args = parser.parse_args()
    args.n = args.n or (8 if args.quick else 96)
    args.batch = args.batch or ([1, 3] if args.quick else [1, 4, 16])
    args.steps = args.steps or (5 if args.quick else 20)
    if args.problem:
        print(json.dumps(run_problem(args)))
        return
    with bench_common.report(__file__, args.out, repeats=args.repeats, n=args.n, steps=args.steps,
                             warmup_steps=args.warmup_steps, batch=args.batch, problems={}) as data:
        for problem in args.problems:
            data["problems"][problem] = run_worker(problem, args)
            print(json.dumps({problem: data["problems"][problem]}, indent=1), flush=True)


if __name__ == "__main__":
    main()
