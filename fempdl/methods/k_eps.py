"""K_eps, the converged cap, on whatever PRDP moves, and the layers a PRDP target moves.

K_eps is the cap that converged solves of given inputs need: the most
iterations of a linear solve, the most Newton steps of a Newton solve (or,
under a :class:`~fempdl.methods.newton_caps.NewtonCaps` rule, the K at which
neither cap cuts a converged solve short). It is measured by running the
inputs through the target with each of its layers' calls solved converged by
that layer's own solver to ``rtol`` (:func:`fempdl.layer.reference.converged_counts`):
a layer, a list of layers, a ``NewtonCaps`` or a ``Rollout`` (every step's
solve counts), with keyword inputs or with ``call=``, any function that
calls the target's layers as the loop does (the validation metric itself).
The target's caps and counters are left as they are.
"""
from __future__ import annotations

from collections.abc import Callable
from contextlib import contextmanager

from mpi4py import MPI
import numpy as np
import torch

from fempdl.core.parallel import batch_size, shard_inputs
from fempdl.layer.cap_target import CapTarget, as_target, layers_target
from fempdl.layer.reference import converged_counts, counters_kept
from fempdl.methods.newton_caps import ConvergedCaps, NewtonCaps
from fempdl.solve.stats import SolverFailedError

__all__ = ["k_eps", "newton_k_eps", "converged_caps", "measure_call", "left_as_is", "remeasured_k_eps"]


@contextmanager
def left_as_is(target: CapTarget):
    """Within the block the target may run at other caps: its caps (``target.kept()``) and its layers'
    counters are put back on exit (probe runs are not training)."""
    with target.kept(), counters_kept(list(target.layers)):
        yield


def _callee(target: CapTarget):
    """What keyword inputs are passed to: the target's layer or rollout."""
    if target.call is None:
        raise TypeError(f"a target over {len(target.layers)} layers: give call= a function that runs them as the "
                        "loop does")
    return target.call


def measure_call(target: CapTarget, call: Callable | None, inputs: dict, what: str) -> Callable[[], object]:
    """The function that runs ``target`` as the loop does: ``call`` itself, or ``target(**inputs)``."""
    if call is not None:
        if inputs:
            raise TypeError(f"give {what} either call= or the target's keyword inputs, not both (got call and "
                            f"{sorted(inputs)})")
        if not callable(call):
            raise TypeError(f"call must be a function that runs the target's layers, got {type(call).__name__}")
        return call
    if not inputs:
        names = [name for layer in target.layers for name in layer.problem.control_names][:1] or ["f"]
        raise ValueError(f"give the inputs to measure {what} on as keyword arguments, e.g. {names[0]}=tensor, or "
                         "call= a function that runs the target's layers")
    callee = _callee(target)
    return lambda: callee(**inputs)


def k_eps(target, *, rtol: float = 1e-8, shard_over: MPI.Comm = MPI.COMM_SELF, batch: int | None = None,
          call: Callable | None = None, **inputs) -> int:
    """K_eps: the cap converged solves need on ``inputs`` (module docstring). Use it as PRDP's ``k_cap``.

    Args:
        target: what PRDP moves: a SolveLayer, a NonlinearSolveLayer (its Newton cap), a NewtonCaps
            (its rule; records ``target.converged``), a Rollout, or a list of layers.
        rtol: the converged solves' tolerance.
        shard_over: keyword inputs are spread over its ranks (data-parallel training, every rank holding
            the whole problem; all of them call) and K_eps is the maximum over the ranks.
        batch: probe keyword inputs in calls of that many samples, as training calls the layer (a
            lagged preconditioner is set up once a call); ``None``: one call.
        call: instead of keyword inputs, a function that runs the target's layers (e.g. the validation).
        inputs: the target's keyword inputs ((B, n) or shared (n,), ``initial_guess`` too when the
            loop warm-starts; a Rollout's ``initial``, ``steps``, ...).

    Example:
        ``ctrl = PRDP(layer, k0=1, dk=1, k_cap=k_eps(layer, f=f_val, rtol=1e-6))``
    """
    target = layers_target(target)
    run = measure_call(target, call, inputs, "K_eps")
    if call is None and all(isinstance(v, torch.Tensor) for v in inputs.values()):
        run = _sharded(run, target, inputs, shard_over, batch)
    return target.k_eps_from(_most_over(converged_counts(list(target.layers), run, rtol), shard_over))


def remeasured_k_eps(target, validate: Callable, rtol: float, step: int) -> int:
    """K_eps of the validation at the current model, as PRDP measures it again at step ``step``; a failed
    converged solve names the measurement and what to do."""
    try:
        return k_eps(target, call=validate, rtol=rtol)
    except SolverFailedError as error:
        raise SolverFailedError(
            f"PRDP measured K_eps again at step {step} (converged solves of the validation at the current model, to "
            f"k_eps_rtol={rtol:g}) and a solve failed: {error}. Keep k_cap as it is with PRDP(..., "
            "remeasure=False), or make the layer's solver converge on these inputs", error.stats) from error


def _most_over(counts: list, comm: MPI.Comm) -> list:
    """Each layer's counts ``(newton_steps or None, iterations)``, the most over the ranks of ``comm``."""
    if comm.size == 1:
        return counts
    mine = np.array([[-1 if n is None else n, k] for n, k in counts], dtype=np.int64)
    most = np.empty_like(mine)
    comm.Allreduce(mine, most, op=MPI.MAX)
    return [(None if n < 0 else int(n), int(k)) for n, k in most]


def _sharded(run, target, inputs: dict, comm: MPI.Comm, batch: int | None):
    """``run`` over this rank's share of the samples, in calls of ``batch`` samples."""
    mine = shard_inputs(inputs, comm)
    samples = batch_size(mine) if any(v.dim() == 2 for v in mine.values()) else 0
    layer = _callee(target)

    def sharded():
        step = batch or max(samples, 1)
        for start in range(0, samples, step):
            layer(**{name: value[start:start + step] if value.dim() == 2 else value for name, value in mine.items()})
    return sharded if comm.size > 1 or batch is not None else run


def converged_caps(layer, *, rtol: float = 1e-8, **controls) -> ConvergedCaps:
    """What converged solves of ``controls`` (a Newton layer's keyword inputs, e.g. validation samples)
    need: the most Newton steps and the most inner iterations of a step (at least 1 each), Newton and
    the inner solve run to ``rtol`` (a direct inner solve as it is)."""
    run = measure_call(as_target(layer), None, controls, "the converged caps")
    (steps, per_step), = converged_counts([layer], run, rtol)
    return ConvergedCaps(max(steps, 1), max(per_step, 1))


def newton_k_eps(caps: NewtonCaps, *, rtol: float = 1e-8, shard_over: MPI.Comm = MPI.COMM_SELF,
                 call: Callable | None = None, **controls) -> int:
    """K_eps of Newton layers under ``caps``' rule: the least K at which converged solves need no more
    than the caps allow (:attr:`NewtonCaps.k_eps`), recorded as ``caps.converged`` (under ``"both"`` they
    bound the caps from then on): :func:`k_eps` on a NewtonCaps."""
    if not isinstance(caps, NewtonCaps):
        raise TypeError(f"caps must be a NewtonCaps, got {type(caps).__name__}")
    return k_eps(caps, rtol=rtol, shard_over=shard_over, call=call, **controls)
