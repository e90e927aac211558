"""The forward alone and forward + gradient of a heat rollout: fempdl's Rollout against a hand-written
DOLFINx loop and dolfinx-adjoint.

The problem: on the unit square (P1, u = 0 on the boundary) N backward-Euler steps of nonlinear heat,

    (u - u_k) / dt - div((1 + u^2) grad u) = f,

from u_0 = 2 sin(pi x) sin(pi y), dt = 0.01, each step's Newton solve warm-started at u_k, with the
loss J = ∫ u_N^2 dx and its gradient with respect to the source f (P1, constant in time).

The sides, each in a fresh process, run the same mathematics (SNES newtonls with a basic line
search, rtol 1e-10, atol 1e-12, MUMPS LU at every Newton step) and take the same Newton steps:

* ``fempdl``: ``Rollout(NonlinearSolveLayer(...))``, then ``loss.backward()``; ``--schedule`` picks
  its adjoint (default: none, one node keeping every state; ``autograd``: a layer call per step); its
  forward alone runs under ``torch.no_grad()``;
* ``fempdl-lagged``: the same with the ``"lu-lagged"`` inner solve: GMRES to 1e-12 on each step's
  own Jacobian, preconditioned by an LU kept across steps and the adjoint's solves;
* ``hand``: a DOLFINx loop by hand (0.11's SNES ``NonlinearProblem``) keeping every state, then a
  reverse loop by hand: J(u_k+1) assembled, a transposed MUMPS solve, the forms -d/df F and
  -d/du_k F assembled at lam; its forward alone is the first loop and J;
* ``dolfinx-adjoint``: the loop on dolfinx-adjoint's ``NonlinearProblem`` / ``LinearProblem``, then
  ``ReducedFunctional(J, Control(f)).derivative()``; its forward alone is the annotated loop and J,
  without the derivative. Install it beside the PyPI stack with
  ``pip install --target <dir> --no-deps dolfinx-adjoint fenicsx-compat pyadjoint-ad h5py`` and pass
  ``--dxa-path <dir>``.

The sides, and how each is timed inside its process, are in ``rollout_sides.py``; this script drives them.

Every side reports J, dJ/df, the Newton steps of one forward + gradient run and of one forward alone
(fempdl's also its inner iterations and lagged LU set-ups, ``preconditioner_refreshes``, of one forward +
gradient run), its peak resident memory and two times, each the minimum of ``--inner-repeats`` runs after a
warm-up (runs of ``--warmup-steps`` steps, which set up and compile all a full one does): ``forward_s``,
the forward rollout and J, and ``forward_gradient_s`` (also ``time_s``), forward and gradient;
``gradient_over_forward`` is what the gradient adds, over the forward. At n >= 200 a side runs
``--big-repeats`` times in one round, which keeps the default run (up to 66,049 DOFs) under about 25
minutes on 2 cores; each row records its repeats and rounds. The driver runs the sides in turn,
``--repeats`` times (rounds, ``bench_common.interleaved``), each side's process timing
``--inner-repeats`` runs, keeps each side's minima, and checks that all sides agree (J to 1e-10, dJ/df to 1e-8
relative) and that each side's forward alone gives the J of its forward + gradient (to 1e-10).
``forward_over_fempdl`` and ``forward_gradient_over_fempdl`` are a side's times over fempdl's (above 1:
fempdl is faster); for the fempdl sides ``forward_vs_dolfinx_adjoint``, ``forward_vs_hand`` and
``forward_gradient_vs_hand`` are their times over the other side's (below 1: fempdl is faster), and
``forward_gradient_speedup_vs_dolfinx_adjoint`` is dolfinx-adjoint's forward + gradient time over
theirs. Writes ``bench-results/bench_rollout.json`` (``--out``) through ``bench_common.report``.

Run (from the repository root, on an idle machine)::

    OMP_WAIT_POLICY=PASSIVE .venv-pypi/bin/python benchmarks/bench_rollout.py --dxa-path /path/to/dxa

A smoke run: ``... --quick --out /tmp/bench_rollout.json``. On the
Debian stack (DOLFINx 0.5) the hand-written side, which needs 0.10's SNES ``NonlinearProblem``, is left out.
"""
from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI  # noqa: F401  (the PyPI stack needs MPI loaded before dolfinx)
from rollout_sides import SIDES

ROOT = Path(__file__).resolve().parent.parent
TIMES = ("forward_s", "forward_gradient_s")
BIG_N = 200           # from this many cells per side a row runs --big-repeats times in one round


# ------------------------------------------------------------------ the driver
def run_side(side: str, n: int, repeats: int, args) -> dict:
    cmd = [sys.executable, __file__, "--side", side, "--n", str(n), "--steps", str(args.steps),
           "--inner-repeats", str(repeats), "--warmup-steps", str(args.warmup_steps)]
    if args.dxa_path:
        cmd += ["--dxa-path", args.dxa_path]
    if args.schedule:
        cmd += ["--schedule", args.schedule]
    out = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    if out.returncode != 0:            # the side's own traceback, which capture_output would hide
        raise SystemExit(f"{' '.join(cmd)} failed:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def keep_best(best: dict, side: str, r: dict) -> None:
    """Keep the side's result of its fastest forward + gradient round, with the fastest forward of any round."""
    if side not in best:
        best[side] = r
        return
    fastest_forward = min(best[side]["forward_s"], r["forward_s"])
    if r["forward_gradient_s"] < best[side]["forward_gradient_s"]:
        best[side] = r
    best[side]["forward_s"] = fastest_forward


def keep_best_run(best: dict, side: str, n: int, inner: int, args) -> float:
    """One round of a side (a fresh process); its forward + gradient seconds."""
    r = run_side(side, n, inner, args)
    keep_best(best, side, r)
    return r["forward_gradient_s"]


def compare(results: dict) -> dict:
    import numpy as np

    ref = results["fempdl"]
    g0 = np.array(ref["grad"])
    out = {}
    for side, r in results.items():
        g = np.array(r["grad"])
        o = out[side] = {
            "forward_s": r["forward_s"], "forward_gradient_s": r["forward_gradient_s"],
            "time_s": r["forward_gradient_s"],
            "gradient_over_forward": (r["forward_gradient_s"] - r["forward_s"]) / r["forward_s"],
            "forward_over_fempdl": r["forward_s"] / ref["forward_s"],
            "forward_gradient_over_fempdl": r["forward_gradient_s"] / ref["forward_gradient_s"],
            "newton_steps": r["newton_steps"], "forward_newton_steps": r["forward_newton_steps"],
            "repeats": r["repeats"], "peak_rss_mib": r["peak_rss_mib"], "loss": r["loss"],
            "loss_rel_diff": abs(r["loss"] - ref["loss"]) / abs(ref["loss"]),
            "forward_loss_rel_diff": abs(r["forward_loss"] - r["loss"]) / abs(r["loss"]),
            "grad_rel_diff": float(np.abs(g - g0).max() / np.abs(g0).max())}
        for key in ("preconditioner_refreshes", "inner_iterations"):
            if key in r:
                o[key] = r[key]
        if o["loss_rel_diff"] > 1e-10 or o["grad_rel_diff"] > 1e-8:
            raise SystemExit(f"{side} disagrees with fempdl: {o}")
        if o["forward_loss_rel_diff"] > 1e-10:
            raise SystemExit(f"{side}'s forward alone disagrees with its forward + gradient: {o}")
    for side in ("fempdl", "fempdl-lagged"):
        if "dolfinx-adjoint" in results:
            dxa = results["dolfinx-adjoint"]
            out[side]["forward_vs_dolfinx_adjoint"] = results[side]["forward_s"] / dxa["forward_s"]
            out[side]["forward_gradient_speedup_vs_dolfinx_adjoint"] = (dxa["forward_gradient_s"]
                                                                        / results[side]["forward_gradient_s"])
        if "hand" in results:
            out[side]["forward_vs_hand"] = results[side]["forward_s"] / results["hand"]["forward_s"]
            out[side]["forward_gradient_vs_hand"] = (results[side]["forward_gradient_s"]
                                                     / results["hand"]["forward_gradient_s"])
    return out


def main() -> None:
    import bench_common

    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=2, quick_repeats=1,
                                 quick="n = 8 and 16, 5 steps, one timed run per process")
    parser.add_argument("--side", choices=list(SIDES))
    parser.add_argument("--n", type=int, nargs="*", default=None,
                        help="cells per side (default 32 96 256; P1 DOFs: (n+1)^2: 1,089, 9,409, 66,049)")
    parser.add_argument("--steps", type=int, default=None, help="time steps (default 100)")
    parser.add_argument("--inner-repeats", type=int, default=None,
                        help="timed runs inside each side's process (default 3)")
    parser.add_argument("--big-repeats", type=int, default=1,
                        help=f"timed runs inside the process at n >= {BIG_N} (and a single round)")
    parser.add_argument("--warmup-steps", type=int, default=2, help="steps of each side's warm-up runs")
    parser.add_argument("--schedule", default=None,
                        help="fempdl's schedule: autograd | all | revolve:<s> (default: one node)")
    parser.add_argument("--dxa-path", default=None, help="where dolfinx-adjoint is installed (else skipped)")
    args = parser.parse_args()
    args.n = args.n or ([8, 16] if args.quick else [32, 96, 256])
    args.steps = args.steps or (5 if args.quick else 100)
    args.inner_repeats = args.inner_repeats or (1 if args.quick else 3)
    if args.schedule and args.schedule.startswith("revolve:"):
        args.schedule_value = ("revolve", int(args.schedule.split(":")[1]))
    else:
        args.schedule_value = args.schedule
    if args.side:
        args.n = args.n[0]
        args.schedule = args.schedule_value
        result = SIDES[args.side](args)
        print(json.dumps(result))
        return
    with bench_common.report(__file__, args.out, repeats=args.repeats, schedule=args.schedule,
                             inner_repeats=args.inner_repeats, big_repeats=args.big_repeats,
                             warmup_steps=args.warmup_steps, rows=[]) as data:
        # The hand-written loop drives 0.10+'s SNES NonlinearProblem: on the Debian stack (0.5) only fempdl runs.
        sides = ["fempdl", "fempdl-lagged"] + (["hand"] if data["machine"]["stack"] != "debian" else []) \
            + (["dolfinx-adjoint"] if args.dxa_path else [])
        for n in args.n:
            inner, rounds = (args.big_repeats, 1) if n >= BIG_N else (args.inner_repeats, args.repeats)
            best: dict = {}
            bench_common.interleaved({side: functools.partial(keep_best_run, best, side, n, inner, args)
                                      for side in sides}, repeats=rounds, warmup=0)
            row = {"dofs": (n + 1) ** 2, "steps": args.steps, "repeats": inner, "rounds": rounds,
                   "warmup_steps": args.warmup_steps, "sides": compare(best)}
            data["rows"].append(row)
            print(json.dumps(row, indent=1), flush=True)


if __name__ == "__main__":
    main()
