"""Benchmark: the marker inverse problem (scene sip-flow), SIP against Adam with backpropagation.

On the scene's physics (:class:`fempdl.app.tasks.marker_rollout.MarkerFlow`):

* single problems: ``--problems`` held-out problems solved from x = 0 by damped
  Gauss-Newton (the SIP inverse, ``--gn-cg`` CG iterations per step) and by
  gradient descent on 1/2 ||P(x) - y||^2 + prior/2 ||x||^2 at each learning rate
  of ``--gd-lr``; recorded: the mean relative marker error after every
  iteration, the iterations to reach each of ``--targets``, the rollouts
  (forward + backward passes) per iteration and the seconds per iteration;
* network training: the scene's network trained with SIP for ``--iterations``
  iterations, then with Adam + backprop for as many, and on until it has used
  SIP's training time (at most ``--max-factor`` times the iterations).
  Recorded every ``--every`` iterations: training time (optimizer steps only),
  the validation velocity error (x space, relative L2) and marker error (y
  space, relative L2). Summary: the ratios SIP / Adam at equal iterations and at
  equal training time, whether SIP's error still falls over its last 20% of
  iterations, the seconds per iteration of both;
* the oracle: the same network and optimizer trained on the proxy loss with
  the true velocity as its target (SIP with an inverse that returns the
  truth): what supervision with the answers reaches in as many iterations.
  The truth holds velocity the marker does not see, which no input
  determines, so the oracle is a reference, not a bound;
* the least-squares reference: the best affine map from (m0, m_T) to v0 over
  the training samples those iterations draw, its held-out velocity error.

With ``--baseline-lr`` only the baseline runs, for ``--iterations`` at each
learning rate given (the check that the comparison's Adam rate is not a weak
one); ``--sip-lr`` does the same for SIP. ``--set section.key=value`` changes
the scene as the command line's ``--set`` does (e.g. ``marker.inputs=raw``).

Torch runs on one thread; OpenMP threads wait passively. Output:
``bench-results/bench_sip_flow.json`` (``--out``), through ``bench_common.report``;
``--quick``: one single problem, 30 gradient-descent steps, no training.
Run: ``python benchmarks/bench_sip_flow.py`` (about 20 minutes on an idle machine).
"""
from __future__ import annotations

import dataclasses
import math
import os
import sys
import time

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")    # before torch starts its threads

import torch  # noqa: E402

from fempdl.app import scene  # noqa: E402
from fempdl.app.tasks.marker import MarkerInversionTask  # noqa: E402
from fempdl.methods.sip import LinearisedGaussNewton, proxy_loss  # noqa: E402

import bench_common  # noqa: E402
from bench_common import comma_list  # noqa: E402


def single_problems(task: MarkerInversionTask, args) -> dict:
    """Gauss-Newton against gradient descent on held-out problems, from x = 0."""
    P, val = task.physics, task.val
    idx = torch.arange(args.problems)
    m0, y = val["m0"][idx], val["y"][idx]
    prior = task.scene.marker.prior

    def marker_error(x):
        with torch.no_grad():
            return float(P.relative_error("marker", P(x, m0), y).mean())

    def velocity_error(x):
        with torch.no_grad():
            return float(P.relative_error("velocity", P.initial_velocity(x), val["v0"][idx]).mean())

    out = {"problems": args.problems, "start_marker_error": marker_error(torch.zeros_like(val["g"][idx])),
           "targets": args.targets, "prior": prior}
    gn = LinearisedGaussNewton(P, prior=prior, max_it=args.gn_cg)
    x, curve, seconds = torch.zeros_like(val["g"][idx]), [], 0.0
    for _ in range(args.gn_steps):
        t0 = time.perf_counter()
        x = gn(x, y, m0=m0)
        seconds += time.perf_counter() - t0
        curve.append({"marker_error": marker_error(x), "velocity_error": velocity_error(x)})
    out["gauss_newton"] = {"cg_iterations": args.gn_cg, "rollouts_per_iteration": {"forward": 1 + args.gn_cg,
                                                                                  "backward": 1 + args.gn_cg},
                           "seconds_per_iteration": seconds / args.gn_steps, "curve": curve,
                           "iterations_to_target": _iterations_to(curve, args.targets)}
    out["gradient_descent"] = {}
    for lr in args.gd_lr:
        x, curve, seconds = torch.zeros_like(val["g"][idx]), [], 0.0
        for it in range(args.gd_steps):
            t0 = time.perf_counter()
            x.requires_grad_(True)
            loss = 0.5 * ((P(x, m0) - y) ** 2).sum() + 0.5 * prior * (x ** 2).sum()
            (grad,) = torch.autograd.grad(loss, x)
            x = (x - lr * grad).detach()
            seconds += time.perf_counter() - t0
            curve.append({"marker_error": marker_error(x), "velocity_error": velocity_error(x)}
                         if (it + 1) % args.gd_every == 0 or it == 0 else None)
            if not math.isfinite(float(x.abs().max())):
                break
        recorded = [(i + 1, c) for i, c in enumerate(curve) if c is not None]
        out["gradient_descent"][str(lr)] = {
            "rollouts_per_iteration": {"forward": 1, "backward": 1}, "seconds_per_iteration": seconds / len(curve),
            "curve": [{"iteration": i, **c} for i, c in recorded],
            "iterations_to_target": {str(t): next((i for i, c in recorded if c["marker_error"] <= t), None)
                                     for t in args.targets},
            "evaluated_every": args.gd_every}
        print(f"GD lr {lr}: marker error {recorded[-1][1]['marker_error']:.4f} after {recorded[-1][0]}", flush=True)
    print(f"GN: marker errors {[round(c['marker_error'], 4) for c in out['gauss_newton']['curve']]}", flush=True)
    return out


def _iterations_to(curve, targets) -> dict:
    return {str(t): next((i + 1 for i, c in enumerate(curve) if c["marker_error"] <= t), None) for t in targets}


class OracleTask(MarkerInversionTask):
    """SIP with an inverse that returns the true velocity: the proxy loss against v0."""

    def __init__(self, scene):
        super().__init__(scene, "sip")

    def loss(self, idx) -> torch.Tensor:
        return proxy_loss(self.model(self.train["inputs"][idx]), self.train["v0"][idx]) / len(idx)


def train(sc, method: str, iterations: int, every: int, time_budget: float | None = None,
          max_iterations: int | None = None) -> dict:
    """Train the scene's network with ``method`` ("sip", "backprop" or "oracle"); the curve of
    (iteration, time, x error, y error)."""
    task = OracleTask(sc) if method == "oracle" else MarkerInversionTask(sc, method)
    steps = math.ceil(task.train_size / sc.optimizer.batch)
    batches = [torch.arange(i, min(i + sc.optimizer.batch, task.train_size))
               for i in range(0, task.train_size, sc.optimizer.batch)]
    val = torch.arange(task.val_size)
    rows = [{"iteration": 0, "train_time": 0.0, "velocity_error": task.validate(),
             "marker_error": float(task.marker_errors(val).mean())}]
    train_time, iteration, epoch = 0.0, 0, 0
    limit = max_iterations or iterations
    while iteration < limit:
        task.start_epoch(epoch)
        t0 = time.perf_counter()
        for idx in batches:
            task.train_step(idx)
        train_time += time.perf_counter() - t0
        iteration += steps
        epoch += 1
        if task.scheduler is not None:
            task.scheduler.step()
        done_time = time_budget is not None and iteration >= iterations and train_time >= time_budget
        if iteration % every == 0 or iteration == iterations or done_time or iteration >= limit:
            rows.append({"iteration": iteration, "train_time": train_time, "velocity_error": task.validate(),
                         "marker_error": float(task.marker_errors(val).mean())})
            print(f"{method} {iteration}: {train_time:.1f} s, velocity error {rows[-1]['velocity_error']:.4f}, "
                  f"marker error {rows[-1]['marker_error']:.4f}", flush=True)
        if time_budget is None and iteration >= iterations:
            break
        if done_time:
            break
    task.close()
    return {"rows": rows, "seconds_per_iteration": train_time / iteration}


def least_squares_reference(sc, iterations: int) -> dict:
    """The affine map (m0, m_T) -> v0 fitted by least squares to the training draws of ``iterations``
    iterations (a ridge of 1e-6 keeps the constant marker columns solvable); its held-out velocity error."""
    task = MarkerInversionTask(sc, "backprop")
    epochs = math.ceil(iterations / math.ceil(task.train_size / sc.optimizer.batch))
    inputs, truths = [], []
    for epoch in range(epochs):
        task.start_epoch(epoch)
        inputs.append(task.train["inputs"])
        truths.append(task.train["v0"])
    X = torch.cat(inputs)
    X = torch.cat([X, torch.ones(len(X), 1, dtype=X.dtype)], dim=1)
    W = torch.linalg.solve(X.T @ X + 1e-6 * torch.eye(X.shape[1], dtype=X.dtype), X.T @ torch.cat(truths))
    val = task.val["inputs"]
    with torch.no_grad():
        v0 = task.physics.initial_velocity(torch.cat([val, torch.ones(len(val), 1, dtype=val.dtype)], dim=1) @ W)
        error = float(task.physics.relative_error("velocity", v0, task.val["v0"]).mean())
    task.close()
    return {"training_samples": len(X), "velocity_error": error}


def summary(sip: dict, adam: dict, iterations: int) -> dict:
    at = lambda rows, n: next(r for r in rows if r["iteration"] >= n)          # noqa: E731
    s_n, a_n = at(sip["rows"], iterations), at(adam["rows"], iterations)
    budget = sip["rows"][-1]["train_time"]
    within = [r for r in adam["rows"] if r["train_time"] <= budget]
    tail = [r["velocity_error"] for r in sip["rows"] if r["iteration"] >= 0.8 * iterations]
    return {
        "iterations": iterations,
        "sip_velocity_error": s_n["velocity_error"], "adam_velocity_error": a_n["velocity_error"],
        "ratio_velocity_equal_iterations": s_n["velocity_error"] / a_n["velocity_error"],
        "sip_marker_error": s_n["marker_error"], "adam_marker_error": a_n["marker_error"],
        "ratio_marker_equal_iterations": s_n["marker_error"] / a_n["marker_error"],
        "sip_still_falling": bool(len(tail) >= 2 and tail[-1] < tail[0]),
        "sip_velocity_error_over_last_20_percent": tail,
        "equal_time_seconds": budget,
        "adam_iterations_in_that_time": within[-1]["iteration"] if within else 0,
        "adam_velocity_error_at_equal_time": within[-1]["velocity_error"] if within else None,
        "ratio_velocity_equal_time": sip["rows"][-1]["velocity_error"] / within[-1]["velocity_error"] if within
        else None,
        "adam_marker_error_at_equal_time": within[-1]["marker_error"] if within else None,
        "seconds_per_iteration": {"sip": sip["seconds_per_iteration"], "adam": adam["seconds_per_iteration"]},
    }


def main(argv=None) -> int:
    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=None,
                                 quick="one single problem, 30 gradient-descent steps, no training")
    parser.add_argument("--scene", default="sip-flow")
    parser.add_argument("--iterations", type=int, default=None, help="default: the scene's epochs x steps")
    parser.add_argument("--every", type=int, default=10)
    parser.add_argument("--max-factor", type=int, default=10)
    parser.add_argument("--problems", type=int, default=4)
    parser.add_argument("--gn-cg", type=int, default=10)
    parser.add_argument("--gn-steps", type=int, default=8)
    parser.add_argument("--gd-lr", type=comma_list(float), default=[1.0, 10.0, 100.0])
    parser.add_argument("--gd-steps", type=int, default=300)
    parser.add_argument("--gd-every", type=int, default=10)
    parser.add_argument("--targets", type=comma_list(float), default=[0.05, 0.02])
    parser.add_argument("--skip-training", action="store_true")
    parser.add_argument("--baseline-lr", type=comma_list(float), default=None,
                        help="only train the baseline, at each of these Adam learning rates")
    parser.add_argument("--sip-lr", type=comma_list(float), default=None,
                        help="only train SIP, at each of these Adam learning rates")
    parser.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE",
                        help="override a scene value (repeatable)")
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args(argv)
    if args.quick:
        args.problems, args.gd_steps, args.skip_training = 1, 30, True
    torch.set_num_threads(args.threads)
    sc = scene.load(args.scene, args.set)
    # nothing is timed repeatedly: training curves and single solves
    with bench_common.report(__file__, args.out, statistic=None, repeats=None, scene=sc.as_dict(),
                             command=" ".join(sys.argv)) as result:
        run(args, sc, result)
    return 0


def run(args, sc, result: bench_common.Report) -> None:
    steps = math.ceil(sc.data.train / sc.optimizer.batch)
    iterations = args.iterations or sc.optimizer.epochs * steps
    sweeps = {"backprop": ("baseline", args.baseline_lr), "sip": ("optimizer", args.sip_lr)}
    if any(rates for _, rates in sweeps.values()):
        result["learning_rate_sweep"] = {}
        for method, (section, rates) in sweeps.items():
            for lr in rates or []:
                swept = dataclasses.replace(sc, **{section: dataclasses.replace(getattr(sc, section), lr=lr)})
                result["learning_rate_sweep"][f"{method} {lr:g}"] = train(swept, method, iterations, args.every)
                result.save()
        return
    task = MarkerInversionTask(sc, "backprop")
    result["sizes"] = {"velocity_dofs": task.physics.velocity_size, "marker_dofs": task.physics.marker_size}
    result["single_problems"] = single_problems(task, args)
    task.close()
    result.save()
    if not args.skip_training:
        sip = train(sc, "sip", iterations, args.every)
        result["training"] = {"sip": sip}
        result.save()
        adam = train(sc, "backprop", iterations, args.every, time_budget=sip["rows"][-1]["train_time"],
                     max_iterations=args.max_factor * iterations)
        result["training"]["adam"] = adam
        result["training"]["oracle"] = train(sc, "oracle", iterations, args.every)
        result["summary"] = summary(sip, adam, iterations)
        result["summary"]["oracle_velocity_error"] = result["training"]["oracle"]["rows"][-1]["velocity_error"]
        result["least_squares_reference"] = least_squares_reference(sc, iterations)
        print(result["summary"], flush=True)


if __name__ == "__main__":
    sys.exit(main())
