"""Benchmark: what a second MPI rank buys, for one big solve layer and for data-parallel training.

(a) Distributed-mesh layer: Poisson on the bundled L-shape at h = 0.00365
    (about 263k P1 DOFs), the source as the control, Richardson + Jacobi capped
    at K = 200 on the PETSc engine, one sample. Timed: the forward solve alone,
    and forward + backward (the adjoint solve and the source gradient), on a
    mesh loaded on COMM_WORLD, with 1 rank and with 2. Each is warmed up
    once and then timed ``--repeats`` times (``bench_common.timed``); the minimum counts (other
    processes only ever add time). Also recorded: DOFs, the owned DOFs of each
    rank, the iterations (the same on any number of ranks).
(b) Data-parallel training (``fempdl run SCENE --parallel data``): each scene
    of ``--scenes`` (default burgers-emulator, whose per-sample GMRES solves
    and matrix assemblies dominate a step, and heat-emulator-2d, whose batched
    Jacobi solves on 1.5k DOFs take a few milliseconds) trained for
    ``--epochs`` epochs at a fixed cap ``--k``, on 1 rank and on 2.
    Throughput = training samples per second of training wall time (the
    slowest rank's; the first epoch, which includes warm-up, is left out);
    the loss curves of the two runs are compared too (they must agree to
    float32 rounding).

Every measurement runs in its own ``mpirun -n R`` job of this script
(``--worker``); the ratios 1 rank / 2 ranks are computed here from one
invocation, so both sides see the same machine. The serial side keeps torch's
default thread count; each of the 2 ranks uses one thread (2 cores).

Writes ``bench-results/bench_mpi.json`` (``--out``, through ``bench_common.report``) and prints the speed-ups.
Run: ``python benchmarks/bench_mpi.py`` (about 3 minutes on 2 cores), or
``--quick`` for a smoke test (h = 0.02, 2 epochs).
"""
from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import numpy as np

from fempdl.core import _dolfinx

import bench_common
from bench_common import comma_list, run_mpi_worker, slowest_rank, timed

RANKS = (1, 2)


# ---------------------------------------------------------------- workers (inside mpirun)
def layer_worker(args) -> dict:
    from mpi4py import MPI
    import torch

    from fempdl import forms, mesh
    from fempdl.bridge_torch import SolveLayer
    from fempdl.ksp_adjoint import KSPOptions

    comm = MPI.COMM_WORLD
    problem = forms.poisson.problem(mesh.load("lshape", comm, h=args.h), controls=("f",))
    layer = SolveLayer(problem, KSPOptions(max_it=args.layer_k, engine="petsc"))
    f = torch.ones(1, problem.control_size("f"), dtype=torch.float64, requires_grad=True)

    def forward():
        with torch.no_grad():
            layer(f=f)

    def forward_backward():
        layer(f=f).square().sum().backward()

    # each warmed up once (form compilation, KSP setup)
    times = {name: timed(slowest_rank(fn), repeats=args.repeats).as_dict()
             for name, fn in (("forward", forward), ("forward_backward", forward_backward))}
    owned = comm.gather(problem.output_size)
    iterations = layer.stats.last.iterations   # of the last (adjoint) solve
    layer.close()
    return {"dofs": int(sum(owned)) if comm.rank == 0 else None, "owned_dofs": owned, "k": args.layer_k,
            "iterations_per_solve": iterations, "times": times}


def training_worker(args) -> dict:
    from mpi4py import MPI  # noqa: F401  (loaded before fempdl.app imports DOLFINx)

    from fempdl.app import scene
    from fempdl.app.runs import runner

    sc = scene.load(args.scene)
    run = runner.run(sc, "fixed", args.k, epochs=args.epochs, parallel="data", k_eps_value=args.k)
    wall = run.wall_time - run.rows[0]["wall_time"]
    samples = sc.data.train * (len(run.rows) - 1)
    return {"scene": sc.name, "k": args.k, "epochs": len(run.rows), "timed_samples": samples, "wall_time": wall,
            "samples_per_second": samples / wall, "train_loss": [row["train_loss"] for row in run.rows],
            "total_iterations": run.total_iterations}


WORKERS = {"layer": layer_worker, "training": training_worker}


def run_worker(args) -> int:
    from mpi4py import MPI

    from fempdl.core import parallel

    parallel.abort_on_error()
    if MPI.COMM_WORLD.size > 1:
        import torch
        torch.set_num_threads(1)   # one core per rank
    result = WORKERS[args.worker](args)
    if MPI.COMM_WORLD.rank == 0:
        Path(args.worker_out).write_text(json.dumps(result))
    return 0


# ---------------------------------------------------------------- driver
def launch(ranks: int, worker: str, args, out: Path, scene: str = "") -> dict:
    return run_mpi_worker(__file__, ranks, ["--worker", worker, "--worker-out", out, "--h", args.h,
                                            "--layer-k", args.layer_k, "--repeats", args.repeats, "--scene", scene,
                                            "--k", args.k, "--epochs", args.epochs], out)


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=5,
                                 quick="h = 0.02, 2 epochs", quick_repeats=2)
    parser.add_argument("--h", type=float, default=0.00365, help="mesh size of the layer benchmark")
    parser.add_argument("--layer-k", type=int, default=200, help="Jacobi iterations of the layer benchmark")
    parser.add_argument("--scenes", type=comma_list(str), default=["burgers-emulator", "heat-emulator-2d"],
                        help="scenes of the training benchmark")
    parser.add_argument("--k", type=int, default=16, help="fixed cap of the training benchmark")
    parser.add_argument("--epochs", type=int, default=5)
    parser.add_argument("--scene", help=argparse.SUPPRESS)
    parser.add_argument("--worker", choices=sorted(WORKERS), help=argparse.SUPPRESS)
    parser.add_argument("--worker-out", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        return run_worker(args)
    if args.quick:
        args.h, args.epochs = 0.02, 2
    try:
        _dolfinx.mpi_launcher()
    except FileNotFoundError as exc:
        parser.error(str(exc))

    settings = {k: v for k, v in vars(args).items() if k not in ("out", "worker", "worker_out")}
    with bench_common.report(__file__, args.out, repeats=args.repeats, settings=settings) as results:
        summarize(args, results)
    print(f"wrote {args.out}")
    return 0


def summarize(args, results: dict) -> None:
    with tempfile.TemporaryDirectory() as tmp:
        layer = {ranks: launch(ranks, "layer", args, Path(tmp) / f"layer{ranks}.json") for ranks in RANKS}
        training = {name: {ranks: launch(ranks, "training", args, Path(tmp) / f"{name}{ranks}.json", name)
                           for ranks in RANKS} for name in args.scenes}
    results["layer"], results["training"] = layer, training
    results["speedup"] = {
        "layer_forward": layer[1]["times"]["forward"]["seconds"] / layer[2]["times"]["forward"]["seconds"],
        "layer_forward_backward": (layer[1]["times"]["forward_backward"]["seconds"]
                                   / layer[2]["times"]["forward_backward"]["seconds"]),
        **{f"training_throughput/{name}": runs[2]["samples_per_second"] / runs[1]["samples_per_second"]
           for name, runs in training.items()},
    }
    for runs in training.values():
        loss1, loss2 = np.array(runs[1]["train_loss"]), np.array(runs[2]["train_loss"])
        runs["loss_max_relative_difference"] = float(np.abs(loss1 - loss2).max() / np.abs(loss1).max())

    print(f"layer: {layer[1]['dofs']} DOFs, Jacobi K={args.layer_k}: forward "
          f"{1e3 * layer[1]['times']['forward']['seconds']:.0f} ms -> "
          f"{1e3 * layer[2]['times']['forward']['seconds']:.0f} ms "
          f"({results['speedup']['layer_forward']:.2f}x), forward + backward "
          f"{1e3 * layer[1]['times']['forward_backward']['seconds']:.0f} ms -> "
          f"{1e3 * layer[2]['times']['forward_backward']['seconds']:.0f} ms "
          f"({results['speedup']['layer_forward_backward']:.2f}x)")
    for name, runs in training.items():
        print(f"training {name}, K={args.k}: {runs[1]['samples_per_second']:.1f} -> "
              f"{runs[2]['samples_per_second']:.1f} samples/s "
              f"({results['speedup'][f'training_throughput/{name}']:.2f}x); "
              f"loss curves agree to {runs['loss_max_relative_difference']:.1e}")


if __name__ == "__main__":
    sys.exit(main())
