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
import resource
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI  # noqa: F401  (the PyPI stack needs MPI loaded before dolfinx)

RTOL, ATOL, DT = 1e-10, 1e-12, 0.01
SNES = {"snes_type": "newtonls", "snes_linesearch_type": "basic", "snes_rtol": RTOL, "snes_atol": ATOL,
        "snes_stol": 0.0, "snes_max_it": 50, "ksp_type": "preonly", "pc_type": "lu",
        "pc_factor_mat_solver_type": "mumps"}
ROOT = Path(__file__).resolve().parent.parent


# ------------------------------------------------------------------ the problem, shared by the sides
def setup(n: int):
    import dolfinx.mesh
    import numpy as np

    from fempdl.core import _dolfinx

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    V = _dolfinx.function_space(msh, "Lagrange", 1)          # either stack's spelling
    x = V.tabulate_dof_coordinates()
    u0 = 2 * np.sin(np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1])
    f = 4 + 2 * np.cos(3 * x[:, 0]) * x[:, 1]
    facets = dolfinx.mesh.locate_entities_boundary(msh, 1, lambda p: np.full(p.shape[1], True))
    bc_dofs = dolfinx.fem.locate_dofs_topological(V, 1, facets)
    return msh, V, u0, f, bc_dofs


def residual(u, u_prev, f, dt):
    import ufl

    v = ufl.TestFunction(u.function_space)
    return ((u - u_prev) / dt * v + (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) - f * v) * ufl.dx


# ------------------------------------------------------------------ the four sides
# Each side builds ``forward(steps) -> J`` (the forward rollout and the loss alone) and ``gradient(steps) ->
# (J, dJ/df)`` (forward and gradient) and hands them to ``timed``.
def side_fempdl(args, ksp: str = "lu"):
    import dolfinx.fem
    import dolfinx.fem.petsc
    import numpy as np
    import scipy.sparse
    import torch
    import ufl

    from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, forms

    msh, V, u0, f, _ = setup(args.n)
    problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=1.0, dt=DT)
    step = NonlinearSolveLayer(problem, NewtonOptions(rtol=RTOL, atol=ATOL, snes_type="newtonls",
                                                      linesearch="basic", ksp=ksp))
    assert problem.V.dofmap.index_map.size_local == len(u0)
    rollout = Rollout(step, "u0", schedule=args.schedule)
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(
        ufl.TrialFunction(V) * ufl.TestFunction(V) * ufl.dx))
    M.assemble()
    indptr, indices, values = M.getValuesCSR()
    csr = scipy.sparse.csr_matrix((values, indices, indptr), shape=M.getSize()).tocoo()
    mass = torch.sparse_coo_tensor(np.vstack([csr.row, csr.col]), csr.data, csr.shape).coalesce()
    initial = torch.tensor(u0)

    def loss_of(source, steps):
        uN = rollout(initial, steps, f=source, outputs=[steps])[-1]
        return uN @ torch.sparse.mm(mass, uN[:, None])[:, 0]

    def forward(steps):
        with torch.no_grad():          # no graph: what a rollout costs when only its states are wanted
            return float(loss_of(torch.tensor(f), steps))

    def gradient(steps):
        source = torch.tensor(f, requires_grad=True)
        loss = loss_of(source, steps)
        loss.backward()
        return float(loss), source.grad.numpy().copy()

    stats = step.system.stats

    def counters():
        return {"newton_steps": getattr(stats, "newton_steps", 0),
                "preconditioner_refreshes": getattr(stats, "preconditioner_refreshes", 0),
                "inner_iterations": stats.forward_iterations + stats.backward_iterations}

    return time_side(forward, gradient, args, counters)


def side_hand(args):
    import dolfinx.fem
    import dolfinx.fem.petsc
    import numpy as np
    import ufl
    from petsc4py import PETSc

    msh, V, u0, f_values, bc_dofs = setup(args.n)
    u, u_prev, f = (dolfinx.fem.Function(V) for _ in range(3))
    f.x.array[:] = f_values
    dt = dolfinx.fem.Constant(msh, DT)
    F = residual(u, u_prev, f, dt)
    bc = dolfinx.fem.dirichletbc(0.0, bc_dofs, V)
    problem = dolfinx.fem.petsc.NonlinearProblem(F, u, bcs=[bc], petsc_options_prefix="hand_",
                                                 petsc_options=dict(SNES))
    # The reverse loop: J(u_k+1)^T lam = g, dJ/df += -dF/df^T lam, g_k = -dF/du_k^T lam.
    lam = dolfinx.fem.Function(V)
    test = F.arguments()[0]
    adjoint_F = ufl.replace(F, {test: lam})
    J_form = dolfinx.fem.form(ufl.derivative(F, u))
    grad_f = dolfinx.fem.form(-ufl.derivative(adjoint_F, f, ufl.TestFunction(V)))
    grad_prev = dolfinx.fem.form(-ufl.derivative(adjoint_F, u_prev, ufl.TestFunction(V)))
    A = dolfinx.fem.petsc.create_matrix(J_form)
    ksp = PETSc.KSP().create(msh.comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    rhs, sol = A.createVecs()
    vec_f, vec_prev = dolfinx.fem.petsc.create_vector(V), dolfinx.fem.petsc.create_vector(V)
    mass = dolfinx.fem.form(u * u * ufl.dx)
    dmass = dolfinx.fem.form(ufl.derivative(u * u * ufl.dx, u, ufl.TestFunction(V)))
    n = len(u0)
    newton = [0]

    def assembled(vec, form):
        with vec.localForm() as local:
            local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(vec, form)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return vec.getArray(readonly=True)[:n].copy()

    def states_and_loss(steps):
        u.x.array[:n] = u0
        u.x.scatter_forward()
        states = [u.x.array.copy()]
        for _ in range(steps):
            u_prev.x.array[:] = states[-1]
            problem.solve()
            newton[0] += problem.solver.getIterationNumber()
            states.append(u.x.array.copy())
        return states, msh.comm.allreduce(dolfinx.fem.assemble_scalar(mass))

    def forward(steps):
        return states_and_loss(steps)[1]       # the states are kept, as the reverse loop would need them

    def gradient(steps):
        states, loss = states_and_loss(steps)
        g = assembled(vec_prev, dmass)
        grad = np.zeros(n)
        for k in range(steps - 1, -1, -1):
            u.x.array[:] = states[k + 1]
            u_prev.x.array[:] = states[k]
            A.zeroEntries()
            dolfinx.fem.petsc.assemble_matrix(A, J_form, [bc])
            A.assemble()
            g[bc_dofs[bc_dofs < n]] = 0.0
            rhs.setArray(g)
            ksp.solveTranspose(rhs, sol)
            lam.x.array[:n] = sol.getArray(readonly=True)
            lam.x.scatter_forward()
            grad += assembled(vec_f, grad_f)
            g = assembled(vec_prev, grad_prev)
        return loss, grad

    return time_side(forward, gradient, args, lambda: {"newton_steps": newton[0]})


def side_dolfinx_adjoint(args):
    sys.path.insert(0, args.dxa_path)
    import dolfinx_adjoint as dxa
    import pyadjoint
    import ufl

    msh, V, u0, f_values, bc_dofs = setup(args.n)
    n = len(u0)
    tape = pyadjoint.get_working_tape()
    newton = [0]

    def annotated_loss(steps):
        """The loop and J on a fresh tape; returns J and the control f."""
        tape.clear_tape()
        f = dxa.Function(V)
        f.x.array[:n] = f_values
        f.x.scatter_forward()
        u, u_prev = dxa.Function(V), dxa.Function(V)
        with pyadjoint.stop_annotating():
            u_prev.x.array[:n] = u0
            u_prev.x.scatter_forward()
            u.x.array[:] = u_prev.x.array
        dt = dxa.Constant(msh, DT)
        F = residual(u, u_prev, f, dt)
        bc = dxa.dirichletbc(dxa.Function(V), bc_dofs)
        problem = dxa.NonlinearProblem(F, u, bcs=[bc], petsc_options=dict(SNES),
                                       adjoint_petsc_options={"ksp_type": "preonly", "pc_type": "lu",
                                                              "pc_factor_mat_solver_type": "mumps"})
        for _ in range(steps):
            problem.solve()
            newton[0] += problem.solver.getIterationNumber()
            dxa.assign(u, u_prev)
        # The problem and states live on until derivative(), as in a user's loop: the tape's adjoint blocks
        # reuse the problem's solvers (with them collected, each block builds its own: 5x the time at 1k DOFs).
        return dxa.assemble_scalar(u * u * ufl.dx), f, (problem, u, u_prev, F, bc, dt)

    def forward(steps):
        # Annotated as a gradient run would be: the forward a dolfinx-adjoint user pays before derivative().
        return float(annotated_loss(steps)[0])

    def gradient(steps):
        J, f, alive = annotated_loss(steps)
        grad = pyadjoint.ReducedFunctional(J, pyadjoint.Control(f)).derivative()
        del alive
        return float(J), grad.x.array[:n].copy()

    return time_side(forward, gradient, args, lambda: {"newton_steps": newton[0]})


def time_side(forward, gradient, args, counters) -> dict:
    """Warm-up runs of ``args.warmup_steps`` steps, then the minimum over ``args.inner_repeats`` of the forward
    alone and of forward + gradient, alternated (``bench_common.interleaved``: a change in the machine's load
    hits both times alike); ``counters()`` (name -> a cumulative count) is read around the first run of each,
    so the counts are those of one run."""
    from bench_common import interleaved

    forward(args.warmup_steps)
    gradient(args.warmup_steps)
    first: dict = {}

    def run_forward() -> None:
        before = counters()
        loss = forward(args.steps)
        first.setdefault("forward", (before, counters(), loss))

    def run_gradient() -> None:
        before = counters()
        loss, grad = gradient(args.steps)
        first.setdefault("gradient", (before, counters(), loss, grad))

    timings = interleaved({"forward": run_forward, "gradient": run_gradient}, repeats=args.inner_repeats, warmup=0)
    (before, middle, forward_loss), (_, after, loss, grad) = first["forward"], first["gradient"]
    counts = {name: after[name] - middle[name] for name in after}
    counts["forward_newton_steps"] = middle["newton_steps"] - before["newton_steps"]
    return {"forward_s": timings["forward"].seconds, "forward_gradient_s": timings["gradient"].seconds,
            "loss": loss, "forward_loss": forward_loss, "grad": grad.tolist(), **counts,
            "repeats": args.inner_repeats,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


SIDES = {"fempdl": side_fempdl, "fempdl-lagged": lambda args: side_fempdl(args, "lu-lagged"), "hand": side_hand,
         "dolfinx-adjoint": side_dolfinx_adjoint}
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
