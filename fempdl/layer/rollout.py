"""A time loop as a layer: N steps u_{k+1} = S(u_k; m_k, c_k) of a step layer whose previous state is a control.

:class:`Rollout` wraps a :class:`~fempdl.layer.solve_layer.SolveLayer` or a
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
rollout (``PRDP(rollout, ...)`` or ``PRDP(step, ...)``). With ``schedule="autograd"``
every step is a call of the step layer and the gradient flows through every
step by autograd, which keeps every state (O(N B n) floats) and works for any
step layer; with a checkpoint schedule (``"all"``, ``("revolve", s)``,
``("multistage", s_ram, s_disk)``) the rollout is one autograd node whose
backward runs the step adjoints under that schedule
(:mod:`fempdl.layer.rollout_checkpoint`): O(s B n) floats, steps run again
counted in :attr:`Rollout.schedule_stats`, the same gradient. A checkpoint
schedule needs a step differentiated implicitly (the step layers' default).
Without a schedule (``None``) a call runs as ``"all"``, the same states kept and
the same gradient with no layer call, operator dispatch or check per step, where
it can: an eager call of an implicit step with no hook on it; under torch.func
transforms or torch.compile (which need the step's operators), for an unrolled
step and for a hooked one, it runs as ``"autograd"``.

``series=`` (a :class:`fempdl.io.TimeSeries`) writes the states to an XDMF time series as the
first sweep computes them (a schedule's recomputed steps write nothing), at the times
t_k = dt_0 + ... + dt_{k-1} of the problem's Constant ``"dt"`` (the step index k without one).

Shapes: ``initial`` (B, n) or (n,); a control constant in time (B, n_m) or
(n_m,); a control per step (B, N, n_m) or (N, n_m) (shared by the batch);
the result (B, T, n), or (T, n) when nothing is batched, for the T indices
``outputs`` into 0 ... N (0: the initial state; default all N + 1).
"""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from contextlib import contextmanager

import numpy as np
import torch

from fempdl.layer.cap_target import LayerCaps
from fempdl.layer.implicit_diff import SECOND_DERIVATIVE_MESSAGE, FirstOrderOnly, count_on_all_ranks
from fempdl.layer.rollout_checkpoint import CheckpointedRollout, ScheduleStats, StatelessRollout, make_schedule
from fempdl.layer.rollout_inputs import checked_call
from fempdl.layer.system_layer import SystemLayer
from fempdl.solve.caps import Caps
from fempdl.solve.linear_system import INITIAL_GUESS
from fempdl.solve.stats import SolverFailedError

__all__ = ["Rollout", "AUTOGRAD"]

#: The schedule that makes every step a call of the step layer, its gradient by autograd through each.
AUTOGRAD = "autograd"


class Rollout(torch.nn.Module):
    """N steps of ``step``, whose control ``state`` is the previous state (module docstring).

    Args:
        step: the step layer (a SolveLayer or a NonlinearSolveLayer).
        state: the name of the step's control that takes the previous state; its space is the
            solution's (``problem.control_size(state) == problem.output_size``).
        warm_start: start each step's solve from the state it advances (``False``: from zero).
        schedule: ``None`` (every state kept: one node where it can, else autograd through every step),
            ``"autograd"`` (every step a call of the step layer), or a checkpoint schedule for the adjoint:
            ``"all"``, ``("revolve", s)``, ``("multistage", s_in_memory, s_on_disk)`` (module docstring).
        disk_dir: where a multistage schedule writes its states on disk (default: the temporary directory).

    Example:
        >>> heat = SolveLayer(forms.heat.problem(msh, controls=("u0", "f")), KSPOptions.preset("cg", max_it=20))
        >>> rollout = Rollout(heat, "u0")
        >>> u = rollout(u_init, steps=50, constants={"dt": dts}, f=f_batch, outputs=[50])   # (B, 1, n)
    """

    def __init__(self, step: SystemLayer, state: str = "u0", *, warm_start: bool = True, schedule=None,
                 disk_dir: str | None = None):
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
        if schedule is not None and schedule != AUTOGRAD:
            make_schedule(schedule, 1)                       # validates the spec
            if isinstance(schedule, tuple):                  # numpy counts kept as python ints (the repr)
                schedule = (schedule[0], *map(int, schedule[1:]))
            if getattr(step, "diff", "implicit") != "implicit":
                raise ValueError("a checkpoint schedule runs the step's implicit adjoint; this step is "
                                 f"diff={step.diff!r} (use schedule=None: autograd keeps its graph)")
        self.step, self.state, self.warm_start = step, state, warm_start
        self.schedule, self.disk_dir = schedule, disk_dir
        #: What the last one-node call ran (:class:`~fempdl.layer.rollout_checkpoint.ScheduleStats`): under a schedule,
        #: or without one where it runs as "all"; a call whose steps are layer calls leaves it as it was.
        self.schedule_stats: ScheduleStats | None = None

    @property
    def layers(self) -> list:
        """The step layer, whose caps every step shares."""
        return [self.step]

    @property
    def max_it(self) -> int | None:
        """The step layer's own cap, shared by every step (assignable)."""
        return self.step.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        self.step.max_it = value

    @property
    def caps(self) -> Caps:
        """The step layer's caps, shared by every step (assignable)."""
        return self.step.caps

    @caps.setter
    def caps(self, caps: Caps) -> None:
        self.step.caps = caps

    def as_target(self) -> LayerCaps:
        """What PRDP moves (:mod:`fempdl.layer.cap_target`): the step layer's cap; keyword inputs call the rollout."""
        return LayerCaps((self.step,), call=self)

    def forward(self, initial: torch.Tensor, steps: int, *, constants: Mapping[str, Sequence[float]] | None = None,
                per_step: Mapping[str, torch.Tensor] | None = None, outputs: Sequence[int] | None = None,
                series=None, **controls: torch.Tensor) -> torch.Tensor:
        """Run ``steps`` steps from ``initial`` (module docstring).

        Args:
            initial: u_0, (B, n) or (n,); differentiable.
            steps: N >= 1.
            constants: per-step values of the problem's Constants, name -> N floats.
            per_step: controls given per step, name -> (B, N, n_m) or (N, n_m).
            outputs: indices into 0 ... N of the states to return (default: all).
            series: a :class:`fempdl.io.TimeSeries` the states are written to (module docstring).
            controls: controls constant in time, (B, n_m) or (n_m,).
        """
        per_step = dict(per_step or {})
        schedule = (self._one_node(initial, controls, per_step) if self.schedule is None
                    else None if self.schedule == AUTOGRAD else self.schedule)
        networks = {name: network.parameters_tensor() for name, network in self.step.problem.networks.items()}
        values, indices = checked_call(self, schedule, initial, steps, constants or {}, controls, per_step, outputs,
                                       networks)
        write = self._writer(series, values, steps)
        write(0, initial)
        if schedule is not None:
            controls = {**controls, **networks}       # a step layer's call would pass them itself
            return _Scheduled.apply(self, schedule, steps, values, tuple(controls), tuple(per_step), indices, write,
                                    initial, *controls.values(), *per_step.values())
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
                write(k + 1, u)
                states.append(u)
        finally:
            for name, value in saved.items():
                problem.constants[name].value = value
        if initial.dim() == 1 and states[-1].dim() == 2:
            states[0] = initial.expand_as(states[-1])        # one initial state shared by a batch
        return torch.stack([states[i] for i in indices], dim=-2)

    def _one_node(self, initial, controls: dict, per_step: dict):
        """``"all"`` where a call without a schedule runs as one node keeping every state, as autograd's graph
        would, without a layer call per step: an eager call of an implicit step, no hook on it. ``None``
        (autograd through every step) under torch.func transforms and torch.compile, which need the
        step's operators, for an unrolled step, and for a step with hooks, which expect its calls."""
        step = self.step
        if (getattr(step.acting(), "diff", "implicit") != "implicit" or torch.compiler.is_compiling()
                or step._forward_hooks or step._forward_pre_hooks
                or torch.nn.modules.module._global_forward_hooks or torch.nn.modules.module._global_forward_pre_hooks):
            return None
        tensors = (initial, *controls.values(), *per_step.values())
        if any(type(t) is not torch.Tensor or torch._C._functorch.is_functorch_wrapped_tensor(t) for t in tensors):
            return None
        return "all"

    def _writer(self, series, values: dict, steps: int):
        """write(k, u_k): to ``series`` at t_k, or nothing."""
        if series is None:
            return lambda k, u: None
        if not callable(getattr(series, "write", None)):
            raise TypeError(f"series must be a fempdl.io.TimeSeries, got {type(series).__name__}")
        dt = self.step.problem.constants.get("dt")
        if "dt" in values:
            dts = values["dt"].reshape(steps)
        elif dt is not None and np.size(dt.value) == 1:
            dts = np.full(steps, float(dt.value))
        else:
            dts = np.ones(steps)
        times = np.concatenate([[0.0], np.cumsum(dts)])
        return lambda k, u: series.write(k, times[k], u, last=k == steps)

    def extra_repr(self) -> str:
        return f"state={self.state!r}, warm_start={self.warm_start}, schedule={self.schedule!r}, max_it={self.max_it}"


class _Scheduled(torch.autograd.Function):
    """The rollout as one node: forward sweep without autograd, backward under the schedule."""

    @staticmethod
    def forward(ctx, rollout, schedule, steps, values, constant_names, step_names, indices, write, initial, *tensors):
        plan = _Plan(rollout, steps, values, constant_names, step_names, initial, tensors)
        training = any(ctx.needs_input_grad[8:])
        plan.layer.note_call(training)

        def run(k, u, first):
            u_next = plan.run(k, u, first, training)
            if first:
                write(k + 1, u_next[0] if plan.unbatched else u_next)
            return u_next
        if plan.adjoint_reads_no_state([n for n, need in zip(plan.names, ctx.needs_input_grad[9:]) if need]):
            runner = StatelessRollout(steps, run, plan.adjoint, indices)
        else:
            runner = CheckpointedRollout(schedule, steps, run, plan.adjoint, indices,
                                         rollout.disk_dir, rollout.step.problem.V.mesh.comm.rank)
        with plan.constants_kept():
            outs = runner.forward(plan.initial)
        rollout.schedule_stats = runner.stats
        ctx.plan, ctx.runner, ctx.indices = plan, runner, indices
        ctx.unbatched = plan.unbatched
        ctx.save_for_backward(initial, *tensors)      # what a gradient of the gradient would depend on
        out = torch.from_numpy(np.stack(outs, axis=1))
        if plan.dtype != torch.float64 and count_on_all_ranks(~torch.isfinite(out.to(plan.dtype)), plan.problem):
            plan.layer._report_overflow(plan.dtype)      # the states are finite in float64, as a step layer says
        return (out[0] if plan.unbatched else out).to(dtype=plan.dtype)

    @staticmethod
    def backward(ctx, grad_out):
        plan, runner = ctx.plan, ctx.runner
        if runner.spent:        # a second backward (retain_graph=True): the schedule runs again from u_0
            runner = ctx.runner = runner.again(lambda k, u, first: plan.run(k, u, False, True))
            with plan.constants_kept(), plan.call_state():     # the states of the forward's inputs
                runner.forward(plan.initial, first=False)
        G = grad_out.detach().to(device="cpu", dtype=torch.float64).numpy()
        G = G[None] if ctx.unbatched else G
        output_grads: dict = {}
        for t, i in enumerate(ctx.indices):
            output_grads[i] = output_grads[i] + G[:, t] if i in output_grads else G[:, t].copy()
        plan.wanted = [name for name, need in zip(plan.names, ctx.needs_input_grad[9:]) if need]
        plan.sums = {}
        with plan.constants_kept(), plan.call_state():
            lam0, per_step = runner.backward(output_grads)
        grads = [plan.reduce(lam0, plan.initial_shared) if ctx.needs_input_grad[8] else None,
                 *plan.control_grads(per_step)]
        grads = [None if g is None else g.to(dtype) for g, dtype in zip(grads, plan.dtypes)]
        anchors = [t for t in (*ctx.saved_tensors, grad_out) if t.requires_grad]
        if torch.is_grad_enabled() and anchors:
            # create_graph=True: the step adjoints are first order; differentiating them again raises
            # instead of silently dropping the second-order terms.
            message = getattr(plan.layer, "second_derivative_message", SECOND_DERIVATIVE_MESSAGE)
            grads = [None if g is None else FirstOrderOnly.apply(g, message, *anchors) for g in grads]
        return (None,) * 8 + tuple(grads)


class _Plan:
    """A scheduled call's arrays and the step's solves and adjoints on them."""

    def __init__(self, rollout, steps, values, constant_names, step_names, initial, tensors):
        # The layer that solves the step's calls now (a twin at reference physics: fempdl.layer.reference).
        self.rollout, self.layer, self.steps, self.values = rollout, rollout.step.acting(), steps, values
        self.system, self.problem = self.layer.system, self.layer.problem
        self.names = list(constant_names) + list(step_names)
        self.per_step = frozenset(step_names)
        self.dtypes = [initial.dtype, *(t.dtype for t in tensors)]
        self.dtype = initial.dtype if all(t.dtype == initial.dtype for t in tensors) else torch.float64
        shapes = [initial.dim() == 2] + [t.dim() == (3 if n in self.per_step else 2)
                                         for n, t in zip(self.names, tensors)]
        sizes = {t.shape[0] for t, batched in zip([initial, *tensors], shapes) if batched}
        if len(sizes) > 1:
            raise ValueError(f"the initial state and the controls have different batch sizes {sorted(sizes)}")
        self.batch = sizes.pop() if sizes else 1
        self.unbatched = not any(shapes)
        self.initial_shared = initial.dim() == 1
        self.shared = {n for n, batched in zip(self.names, shapes[1:]) if not batched}
        self.arrays = {n: np.broadcast_to(_float64(t), (self.batch, *t.shape[-2 if n in self.per_step else -1:]))
                       for n, t in zip(self.names, tensors)}
        self.initial = np.array(np.broadcast_to(_float64(initial), (self.batch, initial.shape[-1])))
        self.caps: dict = {}
        self.wanted: list = []
        self.sums: dict = {}          # dJ/dm of the controls constant in time, summed over the steps
        self.packed = self.layer.call_state.pack(self.system)

    def adjoint_reads_no_state(self, wanted) -> bool:
        """Whether every step's adjoint for the gradients ``wanted`` (and the state's) is free of the states:
        a linear step whose state and wanted controls enter only its right-hand side, linearly."""
        affine = getattr(self.problem, "affine_rhs_controls", None)        # a linear Problem's
        return affine is not None and self.rollout.state in affine and set(wanted) <= affine

    def step_controls(self, k: int, u: np.ndarray) -> dict:
        arrays = {n: (a[:, k] if n in self.per_step else a) for n, a in self.arrays.items()}
        arrays[self.rollout.state] = u
        return arrays

    def set_constants(self, k: int) -> None:
        for name, seq in self.values.items():
            self.problem.constants[name].value = seq[k]

    def run(self, k: int, u: np.ndarray, first: bool, training: bool) -> np.ndarray:
        self.set_constants(k)
        guess = u if self.rollout.warm_start else None
        solve = lambda health=None: self.system.solve(  # noqa: E731
            self.step_controls(k, u), self.batch, frozenset(self.shared), initial_guess=guess, health=health)
        with _at_step(k, self.steps, u, "solve"):
            if first:
                out = self.layer.solve_healthy(solve, training)
                self.caps[k] = self.layer.caps
                return out
            with _caps_set(self.layer, self.caps[k]):
                return solve()

    def adjoint(self, k: int, uk: np.ndarray, uk1: np.ndarray, lam: np.ndarray):
        self.set_constants(k)
        state = self.rollout.state
        with _caps_set(self.layer, self.caps[k]), _at_step(k, self.steps, uk, "adjoint"):
            grads = self.system.adjoint(self.step_controls(k, uk), uk1, lam, [state, *self.wanted],
                                        frozenset(self.shared), initial_guess=self.rollout.warm_start)
        lam_k = grads.pop(state) + grads.pop(INITIAL_GUESS, 0.0)
        for name in [n for n in grads if n not in self.per_step]:     # summed as they come: O(n_m), not O(N n_m)
            g = grads.pop(name)
            self.sums[name] = self.sums[name] + g if name in self.sums else g
        return lam_k, grads

    def control_grads(self, per_step: dict) -> list:
        out = []
        for name in self.names:
            if name not in self.wanted:
                out.append(None)
                continue
            if name in self.per_step:
                g = np.stack([per_step[k][name] for k in range(self.steps)], axis=1)     # (B, N, n_m)
            else:
                g = self.sums[name]
            out.append(self.reduce(g, name in self.shared))
        return out

    def reduce(self, g: np.ndarray, shared: bool) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(g.sum(0) if shared else g))

    @contextmanager
    def constants_kept(self):
        saved = {name: self.problem.constants[name].value.copy() for name in self.values}
        try:
            yield
        finally:
            for name, value in saved.items():
                self.problem.constants[name].value = value

    def call_state(self):
        return self.layer.call_state.restored(self.system, self.packed)


@contextmanager
def _at_step(k: int, steps: int, state: np.ndarray, what: str):
    """Name the step (and the size of the state it started from) in a failed step's error."""
    try:
        yield
    except SolverFailedError as err:
        largest = float(np.max(np.abs(state))) if state.size else 0.0
        grown = ("; the state entering it is not finite" if not np.isfinite(largest) else
                 f"; the state entering it reaches {largest:.3g}" if largest > 1e100 else "")
        raise type(err)(f"step {k} of {steps} ({what}){grown}: {err}", err.stats) from err


@contextmanager
def _caps_set(layer, caps: Caps):
    """The layer at ``caps`` within the block."""
    before = layer.caps
    layer.caps = caps
    try:
        yield
    finally:
        layer.caps = before


def _float64(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).numpy()
