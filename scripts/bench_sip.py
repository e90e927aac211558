"""Benchmark: SIP and HIG against Adam with backpropagation through FEM layers.

Three problems, each trained twice from the same initial network, in one process:

* ``poisson``: a network maps an observed Poisson solution u* (L-shape, P1,
  u = 0 on the boundary) to the source f; truths are random smooth sources
  (zero on the boundary). SIP: proxy loss with the exact inverse
  (:class:`fempdl.sip.ExactLinearInverse`), Adam on the proxy. Baseline: Adam
  on 1/2 ||P(f) - u*||^2 through the layer (LU, exact gradients).
* ``heat``: the same for the initial state u0 of one implicit-Euler heat step
  (dt = 0.05) from a noisy observation (1% noise); SIP with the
  Tikhonov-damped Gauss-Newton inverse (:class:`fempdl.sip.GaussNewtonInverse`).
* ``hig``: a small dense network maps a source to the Poisson solution's
  source again through the layer (coarse L-shape); HIG (kappa = -1/2) against
  Adam on the same loss.

The method runs ``--iterations`` iterations; Adam then runs at least as many
and goes on until it has used the same wall time (at most 20x the
iterations). Recorded per method at every iteration, with the wall time: the
error in x (||x - x_true|| / ||x_true||, SIP problems) on the training and
on held-out samples, or the training loss (HIG); and the ratios method / Adam
at equal iterations and at equal wall time. Writes
``bench-results/bench_sip.json`` (``--out``).
Run: ``python scripts/bench_sip.py`` (about 2 minutes on 2 cores).
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import torch
from mpi4py import MPI

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.experiments import smooth_fields
from fempdl.hig import HIG
from fempdl.ksp_adjoint import KSPOptions
from fempdl.sip import ExactLinearInverse, GaussNewtonInverse, proxy_loss

from bench_common import comma_list, machine_info, write_json_atomically


def _truths(problem, count, seed):
    x = torch.as_tensor(smooth_fields(problem.dof_coordinates(), count, 4, np.random.default_rng(seed)))
    x[:, problem.bc_dofs] = 0.0
    return x


def _network(n, hidden, seed):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(n, hidden), torch.nn.Tanh(), torch.nn.Linear(hidden, n)).double()


def inverse_problem(name: str, args) -> dict:
    """SIP vs Adam on inferring x (source or initial state) from y = P(x) (+ noise)."""
    msh = mesh.load("lshape", MPI.COMM_SELF, h=args.h)
    if name == "poisson":
        problem, control = forms.poisson.problem(msh, controls=("f",)), "f"
    else:
        problem, control = forms.heat.problem(msh, controls=("u0",), dt=0.05), "u0"
    layer = SolveLayer(problem, KSPOptions.preset("lu"))
    x_train, x_val = _truths(problem, args.train, 0), _truths(problem, args.validation, 1)
    with torch.no_grad():
        y_train, y_val = layer(**{control: x_train}), layer(**{control: x_val})
    if name == "heat":
        rng = torch.Generator().manual_seed(2)
        for y in (y_train, y_val):
            noise = 0.01 * y.abs().max() * torch.randn(y.shape, generator=rng, dtype=y.dtype)
            noise[:, problem.bc_dofs] = 0.0
            y += noise
        inverse = GaussNewtonInverse(layer, control, damping=1e-2, max_it=args.gn_iterations)
    else:
        inverse = ExactLinearInverse(layer, control)
    n = problem.output_size
    curves = {}
    for method in ("sip", "adam"):
        model = _network(n, args.hidden, seed=3)
        optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)

        def step():
            x0 = model(y_train)
            if method == "sip":
                loss = proxy_loss(x0, inverse(x0.detach(), y_train))
            else:
                loss = 0.5 * ((layer(**{control: x0}) - y_train) ** 2).sum()
            optimizer.zero_grad()
            loss.backward()
            optimizer.step()

        def measure():
            with torch.no_grad():
                return {"x_error": float((model(y_val) - x_val).norm() / x_val.norm()),
                        "train_x_error": float((model(y_train) - x_train).norm() / x_train.norm())}

        curves[method] = _train(step, measure, args.iterations, curves.get("sip", {}).get("time", [0.0])[-1])
    layer.close()
    return {"dofs": n, **curves, **_ratios(curves, "x_error", "sip", "adam", args.iterations),
            "train": _ratios(curves, "train_x_error", "sip", "adam", args.iterations)}


def hig_problem(args) -> dict:
    """HIG vs Adam: a dense network predicts the source from 4 coefficients; loss on the solution."""
    problem = forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=args.hig_h), controls=("f",))
    layer = SolveLayer(problem, KSPOptions.preset("lu"))
    n = problem.output_size
    truths = _truths(problem, args.hig_batch, 4)
    codes = torch.randn(args.hig_batch, 4, generator=torch.Generator().manual_seed(5), dtype=torch.float64)
    with torch.no_grad():
        targets = layer(f=truths)

    def physics(f):
        return layer(f=f)

    def loss_fn(u):
        return 0.5 * ((u - targets) ** 2).sum(1).mean()

    curves = {}
    for method in ("hig", "adam"):
        torch.manual_seed(6)
        model = torch.nn.Sequential(torch.nn.Linear(4, 16), torch.nn.Tanh(), torch.nn.Linear(16, n)).double()
        if method == "hig":
            hig = HIG(model, lr=args.hig_lr, tau=1e-6)
            step = lambda: hig.step(codes, loss_fn, physics=physics, linear_physics=True)  # noqa: E731
        else:
            optimizer = torch.optim.Adam(model.parameters(), lr=args.lr)

            def step():
                loss = loss_fn(physics(model(codes)))
                optimizer.zero_grad()
                loss.backward()
                optimizer.step()

        def measure():
            with torch.no_grad():
                return {"loss": float(loss_fn(physics(model(codes))))}

        curves[method] = _train(step, measure, args.iterations, curves.get("hig", {}).get("time", [0.0])[-1])
    layer.close()
    return {"dofs": n, "batch": args.hig_batch, **curves, **_ratios(curves, "loss", "hig", "adam", args.iterations)}


def _train(step, measure, iterations: int, time_budget: float) -> dict:
    """Run ``step`` at least ``iterations`` times and until ``time_budget`` seconds (at most 20x the
    iterations); ``measure()`` (not timed) after every step. Returns the measured curves and the times."""
    curves, elapsed = {"time": []}, 0.0
    while len(curves["time"]) < iterations or (elapsed < time_budget and len(curves["time"]) < 20 * iterations):
        start = time.perf_counter()
        step()
        elapsed += time.perf_counter() - start
        curves["time"].append(elapsed)
        for key, value in measure().items():
            curves.setdefault(key, []).append(value)
    return curves


def _ratios(curves: dict, key: str, method: str, baseline: str, iterations: int) -> dict:
    """method / baseline of ``key`` after ``iterations`` iterations each, and at the method's total wall time."""
    a, b = curves[method], curves[baseline]
    t_end = a["time"][-1]
    at_time = max((i for i, t in enumerate(b["time"]) if t <= t_end), default=0)
    return {"ratio_equal_iterations": a[key][iterations - 1] / b[key][iterations - 1],
            "ratio_equal_time": a[key][-1] / b[key][at_time], "equal_time_seconds": t_end,
            "baseline_iterations_in_that_time": at_time + 1}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--h", type=float, default=0.1, help="mesh size of the SIP problems")
    parser.add_argument("--train", type=int, default=64)
    parser.add_argument("--validation", type=int, default=8)
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--lr", type=float, default=1e-3, help="Adam's learning rate (both methods' optimizer)")
    parser.add_argument("--gn-iterations", type=int, default=20, help="CG cap of the heat inverse")
    parser.add_argument("--hig-h", type=float, default=0.3)
    parser.add_argument("--hig-batch", type=int, default=8)
    parser.add_argument("--hig-lr", type=float, default=0.5)
    parser.add_argument("--problems", type=comma_list(str), default=["poisson", "heat", "hig"])
    parser.add_argument("--out", type=Path, default=Path("bench-results/bench_sip.json"))
    args = parser.parse_args(argv)
    results = {"machine": machine_info(), "settings": {k: str(v) for k, v in vars(args).items()}}
    for name in [name for name in ("poisson", "heat") if name in args.problems]:
        results[name] = inverse_problem(name, args)
        r = results[name]
        print(f"{name} ({r['dofs']} DOFs): after {args.iterations} iterations, SIP / Adam x error: "
              f"held-out {r['ratio_equal_iterations']:.3f} (SIP {r['sip']['x_error'][-1]:.3e}), training "
              f"{r['train']['ratio_equal_iterations']:.3f}; at equal time ({r['equal_time_seconds']:.1f} s, "
              f"{r['baseline_iterations_in_that_time']} Adam iterations) held-out {r['ratio_equal_time']:.3f}, "
              f"training {r['train']['ratio_equal_time']:.3f}", flush=True)
    if "hig" not in args.problems:
        write_json_atomically(results, args.out)
        return 0
    results["hig"] = r = hig_problem(args)
    print(f"hig ({r['dofs']} DOFs, batch {r['batch']}): HIG / Adam loss after {args.iterations} iterations "
          f"{r['ratio_equal_iterations']:.3g} (HIG {r['hig']['loss'][-1]:.3e}); at equal time "
          f"({r['equal_time_seconds']:.1f} s, {r['baseline_iterations_in_that_time']} Adam iterations) "
          f"{r['ratio_equal_time']:.3g}")
    write_json_atomically(results, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
