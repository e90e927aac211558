"""Before training: what PRDP can save in a user's own loop, and the caps to give it.

PRDP saves solver work; the wall clock sees the saving only as far as the
solver holds the loop's time. :func:`preflight` measures, on the loop's own
inputs and starts (its ``initial_guess`` too):

* K_eps, the cap converged solves need (``k_cap``): :func:`~fempdl.methods.prdp.k_eps`,
  or :func:`~fempdl.methods.newton_caps.newton_k_eps` for a Newton layer;
* k0, the first cap whose solves are not garbage: :func:`~fempdl.methods.k_start.k_start`, then
  raised as PRDP's health check would raise it on the loop's first training step at k0 (its forward and
  its adjoint solves: a cap whose forward state is within 1% can leave the adjoint garbage);
* the time split of a few of the loop's own steps run at K_eps (real training
  steps): the parts that shrink with the cap (the iterations; where K moves the
  Newton cap, also each Newton step's assembly and set-up) hold a share s of
  the step time;
* c, the cost of solves capped at k0 over solves capped at K_eps, on the inputs:
  k0 / K_eps for a cap that runs exactly K iterations; for a Newton cap, a
  budget that converged solves stop short of, what they ran (from a warm start
  near the solution both may take the same two or three steps, and c is 1).

PRDP never runs below k0, and everything else costs what it did, so it can
save at most s (1 - c) of the wall time (:attr:`Preflight.max_saving`).
Where that is below ``worthwhile``, PRDP cannot pay in this loop and the
report says so: train at K_eps. :meth:`Preflight.summary` prints the
controller to build, with every setting it relies on; :meth:`Preflight.prdp`
builds it (k0 = k_cap = K_eps where PRDP cannot pay: converged caps).
"""
from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Callable

import torch

from fempdl.core.checks import check_int
from fempdl.layer.cap_target import CapTarget, layers_target
from fempdl.methods.k_eps import k_eps, left_as_is, measure_call
from fempdl.methods.k_start import k_start
from fempdl.methods.prdp import PRDP
from fempdl.methods.prdp_settings import PRDPSettings, refined_cap
from fempdl.solve.health import HealthCheck
from fempdl.solve.stats import SolverWarning

__all__ = ["Preflight", "preflight"]


@dataclasses.dataclass(frozen=True)
class Preflight:
    """What :func:`preflight` measured (module docstring); seconds are per step of the loop."""

    k0: int
    k_cap: int
    step_time: float
    capped_time: float
    capped_parts: tuple
    cost_ratio: float
    forward_k0: int | None = None       # k_start's k0, before the first training step's health check

    @property
    def solver_share(self) -> float:
        """s: the share of a step at K_eps that shrinks with the cap."""
        return self.capped_time / self.step_time if self.step_time > 0 else 0.0

    @property
    def max_saving(self) -> float:
        """The most of the wall time PRDP can save: s (1 - c)."""
        return self.solver_share * max(0.0, 1.0 - self.cost_ratio)

    def pays(self, worthwhile: float = 0.1) -> bool:
        return self.max_saving >= worthwhile

    def advice(self, worthwhile: float = 0.1) -> dict:
        """The caps to give PRDP: ``k0`` and ``k_cap`` as measured where PRDP pays; where it cannot,
        ``k0 = k_cap`` = K_eps, so a controller built from them keeps the loop at converged caps."""
        return {"k0": self.k0 if self.pays(worthwhile) else self.k_cap, "k_cap": self.k_cap}

    def prdp(self, target, worthwhile: float = 0.1, **settings) -> PRDP:
        """The controller :meth:`summary` advises: ``PRDP(target, **advice())``, PRDP's defaults for the rest
        (``settings`` override them)."""
        return PRDP(target, **{**self.advice(worthwhile), **settings})

    def summary(self, worthwhile: float = 0.1) -> str:
        raised = "" if self.forward_k0 in (None, self.k0) else \
            f" (k_start's {self.forward_k0}, raised by the health check of a first training step)"
        head = (f"K_eps {self.k_cap}, k0 {self.k0}{raised} (its solves cost {self.cost_ratio:.2f}x those at K_eps); "
                "at K_eps "
                f"the solver ({'+'.join(self.capped_parts)}) holds {100 * self.solver_share:.0f}% of a "
                f"{self.step_time * 1e3:.1f} ms step: PRDP can save at most {100 * self.max_saving:.0f}% of the "
                "wall time")
        call = "PRDP(target, " + ", ".join(f"{key}={value}" for key, value in self.advice(worthwhile).items()) + ")"
        defaults = PRDPSettings()
        relies = (f"its other settings PRDP's defaults, among them growth={defaults.growth:g}, gap={defaults.gap:g}, "
                  f"judge={defaults.judge!r}; call ctrl.step(validate) after every epoch, validate() computing the "
                  "validation metric through the target, and ctrl.finish(validate) after the last")
        if self.pays(worthwhile):
            return f"{head}; use ctrl = {call} (report.prdp(target)), {relies}"
        return (f"{head}, below {100 * worthwhile:.0f}%: PRDP cannot pay in this loop; train at K_eps "
                f"(max_it={self.k_cap}) or with converged solves: ctrl = {call} (report.prdp(target)) keeps the "
                "loop there")


def preflight(step: Callable[[], object], target, *, steps: int = 3, tolerance: float | None = None,
              rtol: float = 1e-8,
              call: Callable | None = None, **inputs) -> Preflight:
    """Measure k0, K_eps and the solver's share of the loop's step (module docstring).

    Args:
        step: runs one training step of the loop (forward, backward, optimizer step) through the
            target's layers; called once at k0 under PRDP's health check, then ``steps + 1`` times at K_eps
            (the first call warms caches up and is not timed). These are real steps: the model trains.
        target: what PRDP will move: a :class:`~fempdl.layer.solve_layer.SolveLayer`, a
            :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` (its Newton cap), a
            :class:`~fempdl.methods.newton_caps.NewtonCaps`, a :class:`~fempdl.layer.rollout.Rollout`,
            or a list of layers (with ``call=``). Its layers' caps are put back afterwards.
        steps: timed steps (>= 1).
        tolerance: k0's relative error (:func:`~fempdl.methods.k_start.k_start`; ``None``: its default).
        rtol: the converged solves' tolerance for K_eps.
        call: instead of keyword inputs, a function that runs the target's layers as the loop does and
            returns what they computed (the validation's outputs, say).
        inputs: the target's keyword inputs as the loop passes them (``initial_guess`` included).
    """
    check_int("steps", steps, minimum=1)
    if not callable(step):
        raise TypeError(f"step must be a callable running one training step, got {type(step).__name__}")
    target = layers_target(target)
    layers = list(target.layers)
    run = measure_call(target, call, inputs, "K_eps")
    parts = ("iterations", "setup", "assembly") if target.counts_newton_steps else ("iterations",)
    k_cap = k_eps(target, rtol=rtol, call=run)
    forward_k0 = min(k_start(target, tolerance=tolerance, rtol=rtol, k_max=k_cap, call=run), k_cap)
    with target.kept():                         # the steps are real training: their counters stay
        k0 = _healthy_start(step, target, forward_k0, k_cap)
        target.set_k(k_cap)
        step()
        before = [_capped_seconds(layer.stats, parts) for layer in layers]
        t0 = time.perf_counter()
        for _ in range(steps):
            step()
        elapsed = time.perf_counter() - t0
        capped = sum(_capped_seconds(layer.stats, parts) - b for layer, b in zip(layers, before))
    cost_ratio = _solve_cost(target, run, k0, parts) / max(_solve_cost(target, run, k_cap, parts), 1)
    return Preflight(k0=k0, k_cap=k_cap, step_time=elapsed / steps, capped_time=capped / steps, capped_parts=parts,
                     cost_ratio=cost_ratio, forward_k0=forward_k0)


def _healthy_start(step: Callable[[], object], target: CapTarget, k0: int, k_cap: int) -> int:
    """k0 as PRDP's health check (its defaults) leaves it after the loop's first training step at k0: raised
    while that step's capped forward or adjoint solves are garbage. The step is a real one (the first of
    the untimed steps); the layers' own health checks are put back."""
    defaults, current = PRDPSettings(), [k0]

    def refine(ratio: float) -> bool:
        if current[0] >= k_cap:
            return False
        current[0] = refined_cap(current[0], defaults, k_cap)
        target.set_k(current[0])
        return True
    layers = target.layers
    kept = [layer.health for layer in layers]
    check = HealthCheck(defaults.health, refine, adjoint_limit=defaults.adjoint_health)
    try:
        for layer in layers:
            layer.health = check
        target.set_k(k0)
        with warnings.catch_warnings():             # a solve the check cannot cure is PRDP's to report
            warnings.simplefilter("ignore", SolverWarning)
            step()
    finally:
        for layer, health in zip(layers, kept):
            layer.health = health
    return current[0]


def _solve_cost(target: CapTarget, run, k: int, parts: tuple) -> int:
    """What ``run()`` ran with the target capped at ``k``: Newton steps where the cap moves them (each repeats
    assembly and set-up), else inner iterations (the target's caps and counters are put back)."""
    layers = target.layers
    with torch.no_grad(), left_as_is(target):
        target.set_k(k)
        before = [_cost(layer.stats, parts) for layer in layers]
        run()
        return sum(_cost(layer.stats, parts) - b for layer, b in zip(layers, before))


def _cost(stats, parts: tuple) -> int:
    return getattr(stats, "newton_steps", 0) if "assembly" in parts else stats.forward_iterations


def _capped_seconds(stats, parts: tuple) -> float:
    seconds = {"iterations": stats.solve_time, "setup": stats.setup_time, "assembly": stats.assembly_time}
    return sum(seconds[part] for part in parts)
