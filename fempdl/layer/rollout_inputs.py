"""The checks of one :class:`~fempdl.layer.rollout.Rollout` call, made once before any step: what the
step layer checks of each of its calls (types, shapes, dtypes; under a schedule, which calls the system
directly, also finite values, positive controls and the caps over a torch.distributed group), the
Constants' per-step values against their bounds, and on a distributed mesh one agreement of the whole
call over the ranks before anything collective runs (ranks that disagree would otherwise wait in
different collectives)."""
from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType

import numpy as np
import torch

from fempdl.core.checks import check_int
from fempdl.core.ranks import torch_group_initialised

__all__ = ["checked_call"]


def checked_call(rollout, schedule, initial, steps: int, constants: Mapping, controls: dict, per_step: dict,
                 outputs, networks: Mapping = MappingProxyType({})) -> tuple[dict, list]:
    """(values, indices): the Constants' per-step values, name -> (N, ...) float64 arrays, and the output
    state indices in 0 ... N, of a checked call (module docstring); a ValueError or TypeError naming the
    argument otherwise. ``schedule``: the call's, ``None`` when every step is a call of the step layer;
    ``networks``: the step's networks' parameters (name -> flat tensor), inputs of every step."""
    check_int("steps", steps, minimum=1)
    values = _constant_values(rollout, constants, steps)
    _check_controls(rollout, controls, per_step, steps)
    indices = _outputs(outputs, steps)
    _check_call(rollout, schedule, initial, steps, values, {**controls, **networks}, per_step, indices)
    return values, indices


def _check_call(rollout, schedule, initial, steps: int, values: dict, controls: dict, per_step: dict,
                indices: list) -> None:
    """The step layer's checks of a step's call, made once for all steps: types, shapes and dtypes, and
    (where no step layer call makes them: under a schedule) finite values, positive controls and the
    caps over a torch.distributed group; the Constants' bounds at every step; and on a distributed mesh
    one agreement of the whole call over the ranks, before anything collective runs."""
    layer = rollout.step
    if not isinstance(initial, torch.Tensor):
        raise TypeError(f"initial must be a torch.Tensor, (B, n) or (n,), got {type(initial).__name__}; wrap "
                        "arrays with torch.as_tensor(..., dtype=torch.float64)")
    n = layer.problem.output_size
    if initial.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"initial has dtype {initial.dtype}; use float32 or float64 (e.g. initial.double())")
    # A rank of a distributed mesh may own no DOFs (n = 0): only an empty batch is refused.
    if initial.dim() not in (1, 2) or initial.shape[-1] != n or (initial.dim() == 2 and initial.shape[0] == 0):
        raise ValueError(f"initial must be (B, {n}) or ({n},): one value per owned DOF of the state's space, got "
                         f"shape {tuple(initial.shape)}")
    one_step = {**controls, **{name: t[..., 0, :] for name, t in per_step.items()}, rollout.state: initial}
    names, tensors, batch, _ = layer._validate(one_step)
    if layer._distributed:
        extra = {"steps": steps, "outputs": tuple(indices), "schedule": repr(schedule),
                 "warm_start": rollout.warm_start, "per-step Constants": {k: v.tolist() for k, v in values.items()}}
        layer._check_ranks_agree(names, tensors, batch, extra, caller="this distributed-mesh Rollout")
    problem = layer.problem
    if schedule is not None:
        whole = {**controls, **per_step, rollout.state: initial}
        layer._check_finite(list(whole), list(whole.values()))
        if torch_group_initialised() and torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            layer._check_caps_over_torch_group()
        problem.check_constants(skip=values)           # those given per step are checked per step below
    problem.check_constants(values)


def _constant_values(rollout, constants: Mapping, steps: int) -> dict:
    problem, values = rollout.step.problem, {}
    if not isinstance(constants, Mapping):
        raise TypeError(f"constants must be a mapping name -> one value per step, got {type(constants).__name__}")
    for name, seq in constants.items():
        if name not in problem.constants:
            raise ValueError(f"the step problem has no Constant {name!r}; its Constants are "
                             f"{sorted(problem.constants)}")
        try:
            # A copy: Constants are taken by value, so an array edited in place after the call changes nothing.
            array = np.array(seq.detach().cpu().numpy() if isinstance(seq, torch.Tensor) else seq, dtype=np.float64)
        except (TypeError, ValueError):
            raise TypeError(f"constants[{name!r}] must be numbers, one per step, got {seq!r}") from None
        shape = np.shape(problem.constants[name].value)
        if array.shape[:1] != (steps,) or array.shape[1:] != shape:
            raise ValueError(f"constants[{name!r}] must hold one value per step, shape {(steps, *shape)}, "
                             f"got {array.shape}")
        if not np.isfinite(array).all():
            raise ValueError(f"constants[{name!r}] has NaN/inf values")
        values[name] = array
    return values


def _check_controls(rollout, controls: dict, per_step: dict, steps: int) -> None:
    problem = rollout.step.problem
    given = sorted((set(controls) | set(per_step)) & set(problem.networks))
    if given:
        raise ValueError(f"{given} name the step's network(s), whose parameters the rollout passes itself (the "
                         "module's current weights, to every step); call it with the controls only")
    names = set(problem.control_names)
    for name in (*controls, *per_step):
        if name == rollout.state:
            raise ValueError(f"{rollout.state!r} is the rollout's state: pass it as `initial`")
        if name not in names:
            raise ValueError(f"unknown control {name!r}; the step's controls are {sorted(names)}")
    both = sorted(set(controls) & set(per_step))
    if both:
        raise ValueError(f"controls {both} are given both constant in time and per step")
    for name, t in per_step.items():
        if not isinstance(t, torch.Tensor) or t.dim() not in (2, 3) or t.shape[-2] != steps:
            shape = tuple(t.shape) if isinstance(t, torch.Tensor) else type(t).__name__
            raise ValueError(f"per_step[{name!r}] must be (B, N, n_m) or (N, n_m) with N = steps = {steps}, "
                             f"got {shape}")


def _outputs(outputs, steps: int) -> list:
    if outputs is None:
        return list(range(steps + 1))
    if isinstance(outputs, (str, int, np.integer)) or not hasattr(outputs, "__iter__"):
        raise TypeError(f"outputs must be a sequence of state indices into 0 ... {steps}, e.g. [{steps}] for the "
                        f"last state, got {outputs!r}")
    indices = list(outputs)
    if not indices or not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool)
                              and -steps - 1 <= i <= steps for i in indices):
        raise ValueError(f"outputs must be state indices in 0 ... {steps} (negative from the end), got {outputs!r}")
    return [int(i) % (steps + 1) for i in indices]
