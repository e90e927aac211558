"""Forward + gradient of a heat rollout: fempdl's Rollout against a hand-written DOLFINx loop and dolfinx-adjoint.

The problem: on the unit square (P1, u = 0 on the boundary) N backward-Euler steps of nonlinear heat,

    (u - u_k) / dt - div((1 + u^2) grad u) = f,

from u_0 = 2 sin(pi x) sin(pi y), dt = 0.01, each step's Newton solve warm-started at u_k, with the
loss J = ∫ u_N^2 dx and its gradient with respect to the source f (P1, constant in time).

The sides, each in a fresh process, run the same mathematics (SNES newtonls with a basic line
search, rtol 1e-10, atol 1e-12, MUMPS LU at every Newton step) and take the same Newton steps:

* ``fempdl``: ``Rollout(NonlinearSolveLayer(...))``, then ``loss.backward()``; ``--schedule`` picks
  its adjoint (default: autograd through every step);
* ``fempdl-lagged``: the same with the ``"lu-lagged"`` inner solve: GMRES to 1e-12 on each step's
  own Jacobian, preconditioned by an LU kept across steps and the adjoint's solves;
* ``hand``: a DOLFINx loop by hand (0.11's SNES ``NonlinearProblem``) keeping every state, then a
  reverse loop by hand: J(u_k+1) assembled, a transposed MUMPS solve, the forms -d/df F and
  -d/du_k F assembled at lam;
* ``dolfinx-adjoint``: the loop on dolfinx-adjoint's ``NonlinearProblem`` / ``LinearProblem``, then
  ``ReducedFunctional(J, Control(f)).derivative()``. Install it beside the PyPI stack with
  ``pip install --target <dir> --no-deps dolfinx-adjoint fenicsx-compat pyadjoint-ad`` and pass
  ``--dxa-path <dir>``.

Every side reports J, dJ/df, its Newton steps, the minimum time of ``--repeats`` forward + gradient
runs after a warm-up, and its peak resident memory. The driver runs the sides in turn, ``--rounds``
times, keeps each side's minimum, and checks that all sides agree (J to 1e-10, dJ/df to 1e-8
relative). ``time_over_fempdl`` is a side's time over fempdl's (above 1: fempdl is faster);
``dolfinx_adjoint_over_this`` is dolfinx-adjoint's time over a fempdl side's. Writes
``bench-results/bench_rollout.json``.

Run (from the repository root, on an idle machine)::

    OMP_WAIT_POLICY=PASSIVE .venv-pypi/bin/python scripts/bench_rollout.py --dxa-path /path/to/dxa
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import subprocess
import sys
import time
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

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    V = dolfinx.fem.functionspace(msh, ("Lagrange", 1))
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


# ------------------------------------------------------------------ the three sides
def side_fempdl(args, ksp: str = "lu"):
    import dolfinx.fem
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

    def run():
        source = torch.tensor(f, requires_grad=True)
        uN = rollout(initial, args.steps, f=source, outputs=[args.steps])[-1]
        loss = uN @ torch.sparse.mm(mass, uN[:, None])[:, 0]
        loss.backward()
        return float(loss), source.grad.numpy().copy()

    stats = step.system.stats
    newton = lambda: getattr(stats, "newton_steps", 0)  # noqa: E731
    result = timed(run, args.repeats, newton)
    result["preconditioner_refreshes"] = getattr(stats, "preconditioner_refreshes", 0)
    result["inner_iterations"] = stats.forward_iterations + stats.backward_iterations
    return result


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
    steps = [0]

    def assembled(vec, form):
        with vec.localForm() as local:
            local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(vec, form)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return vec.getArray(readonly=True)[:n].copy()

    def run():
        u.x.array[:n] = u0
        u.x.scatter_forward()
        states = [u.x.array.copy()]
        for _ in range(args.steps):
            u_prev.x.array[:] = states[-1]
            problem.solve()
            steps[0] += problem.solver.getIterationNumber()
            states.append(u.x.array.copy())
        loss = msh.comm.allreduce(dolfinx.fem.assemble_scalar(mass))
        g = assembled(vec_prev, dmass)
        grad = np.zeros(n)
        for k in range(args.steps - 1, -1, -1):
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

    return timed(run, args.repeats, lambda: steps[0])


def side_dolfinx_adjoint(args):
    sys.path.insert(0, args.dxa_path)
    import dolfinx_adjoint as dxa
    import pyadjoint
    import ufl

    msh, V, u0, f_values, bc_dofs = setup(args.n)
    n = len(u0)
    tape = pyadjoint.get_working_tape()
    steps = [0]

    def run():
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
        for _ in range(args.steps):
            problem.solve()
            steps[0] += problem.solver.getIterationNumber()
            dxa.assign(u, u_prev)
        J = dxa.assemble_scalar(u * u * ufl.dx)
        grad = pyadjoint.ReducedFunctional(J, pyadjoint.Control(f)).derivative()
        return float(J), grad.x.array[:n].copy()

    return timed(run, args.repeats, lambda: steps[0])


def timed(run, repeats: int, newton_steps) -> dict:
    """A warm-up run, then the minimum over ``repeats`` runs; the Newton steps of one run."""
    before = newton_steps()
    loss, grad = run()
    steps = newton_steps() - before
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return {"time_s": min(times), "loss": loss, "grad": grad.tolist(), "newton_steps": steps,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


SIDES = {"fempdl": side_fempdl, "fempdl-lagged": lambda args: side_fempdl(args, "lu-lagged"), "hand": side_hand,
         "dolfinx-adjoint": side_dolfinx_adjoint}


# ------------------------------------------------------------------ the driver
def run_side(side: str, n: int, args) -> dict:
    cmd = [sys.executable, __file__, "--side", side, "--n", str(n), "--steps", str(args.steps),
           "--repeats", str(args.repeats)]
    if args.dxa_path:
        cmd += ["--dxa-path", args.dxa_path]
    if args.schedule:
        cmd += ["--schedule", args.schedule]
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    return json.loads(out.stdout.strip().splitlines()[-1])


def compare(results: dict) -> dict:
    import numpy as np

    ref = results["fempdl"]
    g0 = np.array(ref["grad"])
    out = {}
    for side, r in results.items():
        g = np.array(r["grad"])
        out[side] = {"time_s": r["time_s"], "newton_steps": r["newton_steps"], "peak_rss_mib": r["peak_rss_mib"],
                     "loss": r["loss"], "loss_rel_diff": abs(r["loss"] - ref["loss"]) / abs(ref["loss"]),
                     "grad_rel_diff": float(np.abs(g - g0).max() / np.abs(g0).max()),
                     "time_over_fempdl": r["time_s"] / ref["time_s"]}
        for key in ("preconditioner_refreshes", "inner_iterations"):
            if key in r:
                out[side][key] = r[key]
        if out[side]["loss_rel_diff"] > 1e-10 or out[side]["grad_rel_diff"] > 1e-8:
            raise SystemExit(f"{side} disagrees with fempdl: {out[side]}")
    if "dolfinx-adjoint" in results:
        for side in ("fempdl", "fempdl-lagged"):
            out[side]["dolfinx_adjoint_over_this"] = results["dolfinx-adjoint"]["time_s"] / results[side]["time_s"]
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", choices=list(SIDES))
    parser.add_argument("--n", type=int, nargs="*", default=[32, 96], help="cells per side (P1 DOFs: (n+1)^2)")
    parser.add_argument("--steps", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--schedule", default=None, help="fempdl's schedule: all | revolve:<s> (default: autograd)")
    parser.add_argument("--dxa-path", default=None, help="where dolfinx-adjoint is installed (else skipped)")
    args = parser.parse_args()
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
    from bench_common import machine_info, write_json_atomically

    sides = ["fempdl", "fempdl-lagged", "hand"] + (["dolfinx-adjoint"] if args.dxa_path else [])
    rows = []
    for n in args.n:
        best: dict = {}
        for _ in range(args.rounds):
            for side in sides:
                r = run_side(side, n, args)
                if side not in best or r["time_s"] < best[side]["time_s"]:
                    best[side] = r
        row = {"dofs": (n + 1) ** 2, "steps": args.steps, "sides": compare(best)}
        rows.append(row)
        print(json.dumps(row, indent=1), flush=True)
    data = {"date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
            "machine": machine_info(), "schedule": args.schedule, "repeats": args.repeats, "rounds": args.rounds,
            "rows": rows}
    write_json_atomically(data, ROOT / "bench-results" / "bench_rollout.json")


if __name__ == "__main__":
    main()
