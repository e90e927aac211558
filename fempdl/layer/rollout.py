"""A time loop as a layer: N steps u_{k+1} = S(u_k; m_k, c_k) of a step layer whose previous state is a control.

:class:`Rollout` wraps a :class:`~fempdl.bridge_torch.SolveLayer` or a
:class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` whose problem takes the
previous state as the control ``state`` (``"u0"`` in the bundled heat and
nonlinear-diffusion steps) and runs

    u_0 = initial,   u_{k+1} = S(u_k; m_k, c_k),   k = 0 ... N - 1,

where m_k are the step's other controls, constant in time or given per step,
and c_k the values of the problem's Constants for step k (a dt sequence),
taken by value: each step's backward runs at the values its forward read
(:class:`~fempdl.solve.call_state.CallState`), so a varying dt gives the exact
gradient by construction. Each step starts its solve from the state it
advances (``initial_guess=u_k``, differentiable), as time steppers do.

The step layer's caps apply to every step; PRDP moves them for the whole
rollout (``PRDP(rollout, ...)`` or ``PRDP(step, ...)``). The gradient flows
through every step by autograd, which keeps every state (O(N B n) floats).

Shapes: ``initial`` (B, n) or (n,); a control constant in time (B, n_m) or
(n_m,); a control per step (B, N, n_m) or (N, n_m) (shared by the batch);
the result (B, T, n), or (T, n) when nothing is batched, for the T indices
``outputs`` into 0 ... N (0: the initial state; default all N + 1).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import torch

from fempdl.core.checks import check_int
from fempdl.layer.system_layer import SystemLayer

__all__ = ["Rollout"]


class Rollout(torch.nn.Module):
    """N steps of ``step``, whose control ``state`` is the previous state (module docstring).

    Args:
        step: the step layer (a SolveLayer or a NonlinearSolveLayer).
        state: the name of the step's control that takes the previous state; its space is the
            solution's (``problem.control_size(state) == problem.output_size``).
        warm_start: start each step's solve from the state it advances (``False``: from zero).

    Example:
        >>> heat = SolveLayer(forms.heat.problem(msh, controls=("u0", "f")), KSPOptions.preset("cg", max_it=20))
        >>> rollout = Rollout(heat, "u0")
        >>> u = rollout(u_init, steps=50, constants={"dt": dts}, f=f_batch, outputs=[50])   # (B, 1, n)
    """

    def __init__(self, step: SystemLayer, state: str = "u0", *, warm_start: bool = True):
        super().__init__()
        if not isinstance(step, SystemLayer):
            raise TypeError(f"step must be a SolveLayer or a NonlinearSolveLayer, got {type(step).__name__}")
        problem = step.problem
        if state not in problem.control_names:
            raise ValueError(f"the step has no control {state!r} to take the previous state; its controls are "
                             f"{list(problem.control_names)} (build the step problem with controls=({state!r}, ...))")
        if problem.control_size(state) != problem.output_size:
            raise ValueError(f"control {state!r} has {problem.control_size(state)} values per sample but the state has "
                             f"{problem.output_size}: the previous state must live in the solution's space")
        if not isinstance(warm_start, bool):
            raise TypeError(f"warm_start must be True or False, got {warm_start!r}")
        self.step, self.state, self.warm_start = step, state, warm_start

    @property
    def layers(self) -> list:
        """The step layer, as PRDP looks for the layers a target moves."""
        return [self.step]

    @property
    def max_it(self):
        """The step layer's cap, shared by every step (assignable: PRDP moves it)."""
        return self.step.max_it

    @max_it.setter
    def max_it(self, value) -> None:
        self.step.max_it = value

    def forward(self, initial: torch.Tensor, steps: int, *, constants: Mapping[str, Sequence[float]] | None = None,
                per_step: Mapping[str, torch.Tensor] | None = None, outputs: Sequence[int] | None = None,
                **controls: torch.Tensor) -> torch.Tensor:
        """Run ``steps`` steps from ``initial`` (module docstring).

        Args:
            initial: u_0, (B, n) or (n,); differentiable.
            steps: N >= 1.
            constants: per-step values of the problem's Constants, name -> N floats.
            per_step: controls given per step, name -> (B, N, n_m) or (N, n_m).
            outputs: indices into 0 ... N of the states to return (default: all).
            controls: controls constant in time, (B, n_m) or (n_m,).
        """
        check_int("steps", steps, minimum=1)
        per_step = dict(per_step or {})
        values = self._constant_values(constants or {}, steps)
        self._check_controls(controls, per_step, steps)
        indices = self._outputs(outputs, steps)
        problem = self.step.problem
        saved = {name: problem.constants[name].value.copy() for name in values}
        u, states = initial, [initial]
        try:
            for k in range(steps):
                for name, seq in values.items():
                    problem.constants[name].value = seq[k]
                inputs = {**controls, **{name: t[..., k, :] for name, t in per_step.items()}}
                if self.warm_start:
                    inputs["initial_guess"] = u
                u = self.step(**inputs, **{self.state: u})
                states.append(u)
        finally:
            for name, value in saved.items():
                problem.constants[name].value = value
        return torch.stack([states[i] for i in indices], dim=-2)

    def _constant_values(self, constants: Mapping, steps: int) -> dict:
        problem, values = self.step.problem, {}
        for name, seq in constants.items():
            if name not in problem.constants:
                raise ValueError(f"the step problem has no Constant {name!r}; its Constants are "
                                 f"{sorted(problem.constants)}")
            array = np.asarray(seq.detach().cpu() if isinstance(seq, torch.Tensor) else seq, dtype=np.float64)
            shape = np.shape(problem.constants[name].value)
            if array.shape[:1] != (steps,) or array.shape[1:] != shape:
                raise ValueError(f"constants[{name!r}] must hold one value per step, shape {(steps, *shape)}, "
                                 f"got {array.shape}")
            if not np.isfinite(array).all():
                raise ValueError(f"constants[{name!r}] has NaN/inf values")
            values[name] = array
        return values

    def _check_controls(self, controls: dict, per_step: dict, steps: int) -> None:
        names = set(self.step.problem.control_names)
        for name in (*controls, *per_step):
            if name == self.state:
                raise ValueError(f"{self.state!r} is the rollout's state: pass it as `initial`")
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

    @staticmethod
    def _outputs(outputs, steps: int) -> list:
        if outputs is None:
            return list(range(steps + 1))
        indices = list(outputs)
        if not indices or not all(isinstance(i, (int, np.integer)) and not isinstance(i, bool)
                                  and -steps - 1 <= i <= steps for i in indices):
            raise ValueError(f"outputs must be state indices in 0 ... {steps} (negative from the end), got {outputs!r}")
        return [int(i) % (steps + 1) for i in indices]

    def extra_repr(self) -> str:
        return f"state={self.state!r}, warm_start={self.warm_start}, max_it={self.max_it}"
