"""Benchmark: a 3D Poisson layer at scale, forward + backward, on 1 and 2 MPI ranks.

The bundled unit box meshed at each ``--h`` (default 0.022 and 0.009: about
1e5 and 1e6 P1 DOFs; meshed once into a temporary .msh file, outside the
timing), Poisson with the source as the control, the ``--preset`` solver
(default "amg": CG + BoomerAMG, or GAMG without hypre) to ``--rtol``. Timed
per size and rank count, each in its own ``mpirun -n R`` job of this script:
the layer's construction (assembly, solver set-up), and forward + backward
(the solve, the adjoint solve, the source gradient) for one sample, warmed up
once, then the minimum of ``--repeats`` (``bench_common.timed``). Recorded: DOFs, iterations, the peak
resident memory of each rank (``ru_maxrss``; rank 0 reads the whole .msh),
the memory each rank holds after the solves above its state after the
imports, and, per size, the speed-up and
parallel efficiency of 2 ranks and their memory per rank against 1 rank.

Writes ``bench-results/bench_scale.json`` (``--out``) through ``bench_common.report``;
run on an idle machine. ``--quick``: h = 0.08 and 0.05, for a smoke test.
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import bench_common
from bench_common import comma_list, run_mpi_worker, slowest_rank, timed

RANKS = (1, 2)


def worker(args) -> int:
    from mpi4py import MPI
    import torch

    from fempdl import forms, mesh
    from fempdl.bridge_torch import SolveLayer
    from fempdl.core import parallel
    from fempdl.ksp_adjoint import KSPOptions

    parallel.abort_on_error()
    comm = MPI.COMM_WORLD
    baseline = current_rss_mib()                          # the interpreter, torch, DOLFINx, PETSc
    torch.set_num_threads(1 if comm.size > 1 else torch.get_num_threads())
    tagged = mesh.load(args.msh, comm)
    t0 = time.perf_counter()
    problem = forms.poisson.problem(tagged, controls=("f",), dirichlet=None)
    layer = SolveLayer(problem, KSPOptions.preset(args.preset, rtol=args.rtol))
    f = torch.ones(problem.control_size("f"), dtype=torch.float64, requires_grad=True)
    layer(f=f).square().sum().backward()                  # warm-up: compilation, assembly, set-up
    setup = comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)

    def forward_backward() -> None:
        f.grad = None
        layer(f=f).square().sum().backward()

    timing = timed(slowest_rank(forward_backward, comm), repeats=args.repeats, warmup=0)
    peak_mib = comm.gather(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0)
    held_mib = comm.gather(current_rss_mib() - baseline)  # what the mesh, system and solver hold now
    result = {"dofs": comm.allreduce(problem.output_size), "ranks": comm.size, "setup_seconds": setup,
              "forward_backward_seconds": timing.seconds, "all_seconds": list(timing.samples),
              "forward_iterations": layer.stats.max_forward_iterations,
              "backward_iterations": layer.stats.last.iterations, "peak_rss_mib_per_rank": peak_mib,
              "held_mib_per_rank": held_mib, "baseline_mib": baseline}
    layer.close()
    if comm.rank == 0:
        Path(args.worker_out).write_text(json.dumps(result))
    return 0


def current_rss_mib() -> float:
    """This process's resident memory now (the peak also counts rank 0 reading the whole .msh)."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2.0 ** 20


def launch(ranks: int, msh: Path, args, out: Path) -> dict:
    return run_mpi_worker(__file__, ranks, ["--worker", "--msh", msh, "--worker-out", out, "--preset", args.preset,
                                            "--rtol", args.rtol, "--repeats", args.repeats], out)


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=3, quick="h = 0.08 and 0.05",
                                 quick_repeats=1)
    parser.add_argument("--h", type=comma_list(float), default=[0.022, 0.009], help="box mesh sizes")
    parser.add_argument("--preset", default="amg")
    parser.add_argument("--rtol", type=float, default=1e-8)
    parser.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--msh", help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return worker(args)
    if args.quick:
        args.h = [0.08, 0.05]

    with bench_common.report(__file__, args.out, repeats=args.repeats, preset=args.preset, rtol=args.rtol,
                             sizes=[]) as report:
        measure(args, report["sizes"])
    return 0


def measure(args, sizes: list) -> None:
    from fempdl.core import meshgen

    with tempfile.TemporaryDirectory() as tmp:
        for h in args.h:
            msh = Path(tmp) / f"box-{h}.msh"
            t0 = time.perf_counter()
            meshgen.write_msh("box", msh, h=h)
            meshing = time.perf_counter() - t0
            runs = {ranks: launch(ranks, msh, args, Path(tmp) / f"out-{h}-{ranks}.json") for ranks in RANKS}
            one, two = runs[1], runs[2]
            speedup = one["forward_backward_seconds"] / two["forward_backward_seconds"]
            row = {"h": h, "dofs": one["dofs"], "meshing_seconds": meshing, "runs": runs,
                   "speedup_2_ranks": speedup, "parallel_efficiency_2_ranks": speedup / 2,
                   "peak_memory_per_rank_2_over_1": max(two["peak_rss_mib_per_rank"]) / one["peak_rss_mib_per_rank"][0],
                   "held_memory_per_rank_2_over_1": max(two["held_mib_per_rank"]) / one["held_mib_per_rank"][0]}
            sizes.append(row)
            print(f"h={h}: {row['dofs']} DOFs, fwd+bwd {one['forward_backward_seconds']:.2f} s on 1 rank, "
                  f"{two['forward_backward_seconds']:.2f} s on 2 (speed-up {speedup:.2f}x, efficiency "
                  f"{speedup / 2:.0%}); iterations {one['forward_iterations']}/{two['forward_iterations']}; "
                  f"memory held per rank {one['held_mib_per_rank'][0]:.0f} MiB -> "
                  f"{max(two['held_mib_per_rank']):.0f} MiB ({row['held_memory_per_rank_2_over_1']:.2f}x), peak "
                  f"{one['peak_rss_mib_per_rank'][0]:.0f} -> {max(two['peak_rss_mib_per_rank']):.0f} MiB",
                  flush=True)


if __name__ == "__main__":
    sys.exit(main())
