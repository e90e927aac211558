"""The gradient of a long 3D heat rollout under a checkpoint schedule, in bounded memory.

A backward-Euler heat rollout on the unit cube (P1, u = 0 on the boundary, (n+1)^3 DOFs: 103,823 at
the default n = 46) of N steps (default 5,000), from u_0 = sin(pi x) sin(pi y) sin(pi z), with a
source f (P1, constant in time) and the loss J = sum of u_N^2 over the DOFs. Storing every state
would hold N (n+1)^3 floats: 3.9 GiB at the defaults. Each step is ``SolveLayer`` with CG + Jacobi to
rtol 1e-10 (the heat matrix M + dt K is well conditioned at dt = 2e-4).

Each schedule runs in its own process, which reports the peak resident memory above what the
process held once the imports and the problem were set up (``ru_maxrss`` before and after the
forward + gradient), the forward and backward times, the schedule's statistics and dJ/df. The
driver compares the gradients: under ``("revolve", s)`` it must equal the store-every-state gradient
(``"all"``) to 1e-12 relative. Writes ``bench-results/demo_rollout_memory.json`` (``--out``) through
``bench_common.report``; ``--quick``: n = 10, 50 steps.

The heat step is linear and f enters its right-hand side only: the adjoint of a step reads no state,
so the rollout keeps none and runs no step again under either schedule
(:class:`fempdl.layer.rollout_checkpoint.StatelessRollout`); ``schedule_stats`` shows it.

Run (from the repository root; about 20 minutes a schedule on 2 cores)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/demo_rollout_memory.py [--schedules revolve]
"""
from __future__ import annotations

import json
import resource
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI  # noqa: F401  (the PyPI stack needs MPI loaded before dolfinx)
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
DT = 2e-4


def peak_mib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_schedule(args) -> dict:
    import dolfinx.mesh
    import torch

    from fempdl import KSPOptions, Rollout, SolveLayer, forms

    msh = dolfinx.mesh.create_unit_cube(MPI.COMM_WORLD, args.n, args.n, args.n)
    problem = forms.heat.problem(msh, controls=("u0", "f"), dt=DT)
    step = SolveLayer(problem, KSPOptions.preset("cg"))
    x = problem.dof_coordinates()
    u0 = torch.tensor(np.prod(np.sin(np.pi * x), axis=1))
    f = torch.tensor(1 + x[:, 0] * x[:, 1], requires_grad=True)
    schedule = args.schedule if args.schedule == "all" else ("revolve", args.snapshots)
    rollout = Rollout(step, "u0", schedule=schedule)
    before = peak_mib()
    t0 = time.perf_counter()
    uN = rollout(u0, args.steps, f=f, outputs=[args.steps])
    loss = uN.square().sum()
    forward = time.perf_counter() - t0
    loss.backward()
    elapsed = time.perf_counter() - t0
    np.save(args.grad_out, f.grad.numpy())
    stats = rollout.schedule_stats
    return {"schedule": str(schedule), "dofs": problem.output_size, "steps": args.steps, "loss": float(loss),
            "time_s": elapsed, "forward_s": forward, "backward_s": elapsed - forward,
            "peak_above_setup_mib": peak_mib() - before, "setup_peak_mib": before,
            "states_all_gib": args.steps * problem.output_size * 8 / 2 ** 30,
            "schedule_stats": {k: getattr(stats, k) for k in ("steps", "recomputed", "reused", "adjoint_steps",
                                                               "most_in_memory", "most_on_disk")},
            "cg_iterations_per_solve": (step.stats.forward_iterations + step.stats.backward_iterations)
            / max(step.stats.forward_solves + step.stats.backward_solves, 1)}


def main() -> None:
    import bench_common

    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=None, quick="n = 10, 50 steps")
    parser.add_argument("--n", type=int, default=None, help="cells per edge of the cube (default 46)")
    parser.add_argument("--steps", type=int, default=None, help="default 5000")
    parser.add_argument("--snapshots", type=int, default=100, help="revolve's snapshots in memory")
    parser.add_argument("--schedule", choices=["all", "revolve"], default=None, help="(one process's part)")
    parser.add_argument("--schedules", nargs="+", choices=["revolve", "all"], default=["revolve", "all"],
                        help="the schedules to run (the gradients are compared when both run)")
    parser.add_argument("--grad-out", default=None)
    args = parser.parse_args()
    args.n = args.n or (10 if args.quick else 46)
    args.steps = args.steps or (50 if args.quick else 5000)
    if args.schedule:
        print(json.dumps(run_schedule(args)))
        return
    # one run per schedule: memory and its times, nothing timed repeatedly
    with bench_common.report(__file__, args.out, statistic=None, repeats=None) as data:
        data.update(run_schedules(args))
    print(json.dumps({k: data[k] for k in ("grad_rel_diff_revolve_vs_all", "met")}))


def run_schedules(args) -> dict:
    runs, grads = {}, {}
    for schedule in args.schedules:
        out = ROOT / "runs" / f"demo_rollout_memory_{schedule}.npy"
        out.parent.mkdir(exist_ok=True)
        cmd = [sys.executable, __file__, "--schedule", schedule, "--n", str(args.n), "--steps", str(args.steps),
               "--snapshots", str(args.snapshots), "--grad-out", str(out)]
        result = subprocess.run(cmd, check=True, capture_output=True, text=True)
        runs[schedule] = json.loads(result.stdout.strip().splitlines()[-1])
        grads[schedule] = np.load(out)
        out.unlink()
        print(json.dumps(runs[schedule], indent=1), flush=True)
    diff = (float(np.abs(grads["revolve"] - grads["all"]).max() / np.abs(grads["all"]).max())
            if len(grads) == 2 else None)
    return {"runs": runs, "grad_rel_diff_revolve_vs_all": diff,
            "target": "revolve: at most 1024 MiB above set-up; gradient equal to 'all' to 1e-12",
            "met": runs["revolve"]["peak_above_setup_mib"] <= 1024 and (diff is None or diff <= 1e-12)}


if __name__ == "__main__":
    main()
