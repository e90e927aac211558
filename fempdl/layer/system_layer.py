"""What fempdl's solve layers share: controls as keyword tensors, checks, collective calls, the cap in
``state_dict``, the health check of capped training solves, and the PETSc objects' lifetime.

:class:`SystemLayer` is the base of :class:`~fempdl.layer.solve_layer.SolveLayer` (a linear system) and
:class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` (a Newton solve). A subclass calls
:meth:`SystemLayer._init_system` with its problem and system; the system has ``stats``,
``options``/``caps``, ``solve``/``adjoint`` on arrays and ``destroy``. A layer's caps are one
:class:`~fempdl.solve.caps.Caps` value (``layer.caps``), which PRDP moves through :meth:`SystemLayer.as_target`.

Shapes: each control tensor is (B, n_m) or (n_m,) with n_m = ``problem.control_size(name)``; a
(n_m,) tensor is shared by all samples; ``initial_guess`` is (B, n) or (n,).
"""
from __future__ import annotations

import dataclasses
import hashlib
import weakref
from collections.abc import Callable

import numpy as np
import torch

from fempdl.core.ranks import different_metrics_message, torch_group_initialised, training_ranks
from fempdl.layer.cap_target import LayerCaps
from fempdl.layer.healthy_calls import HealthyCalls
from fempdl.layer.implicit_diff import ImplicitSolve, count_on_all_ranks, nonfinite_control_message, register_layer
from fempdl.solve.call_state import CallState
from fempdl.solve.caps import Caps
from fempdl.solve.health import CallHealth, HealthCheck
from fempdl.solve.linear_system import INITIAL_GUESS
from fempdl.solve.stats import CumulativeStats, warn_at_caller

__all__ = ["SystemLayer", "INITIAL_GUESS", "DIFF_MODES", "check_diff"]

#: How a solve layer's backward differentiates: the implicit gradient at the returned state, or the
#: reverse pass of the capped iteration that ran.
DIFF_MODES = ("implicit", "unrolled")

_FLOAT_DTYPES = (torch.float32, torch.float64)


def check_diff(diff) -> None:
    if diff not in DIFF_MODES:
        raise ValueError(f"diff must be one of {list(DIFF_MODES)}, got {diff!r}")


def _nobody() -> None:
    """The controller of a layer no PRDP moves."""
    return None


class SystemLayer(torch.nn.Module):
    """The common part of the solve layers (module docstring)."""

    def _init_system(self, problem, system) -> None:
        self.problem = problem
        self._system = system
        self.call_state = CallState(problem)
        # Plain values for forward, so torch.compile traces it without entering the Problem.
        self._distributed = problem.V.mesh.comm.size > 1
        self._sizes = {**{n: problem.control_size(n) for n in problem.control_names},
                       INITIAL_GUESS: problem.output_size,
                       **{n: network.parameter_count for n, network in problem.networks.items()}}
        if problem.networks:
            # Submodules: the networks' weights are the model's parameters (model.parameters(), state_dict).
            self.networks = torch.nn.ModuleDict({n: network.module for n, network in problem.networks.items()})
        self._handle = register_layer(self)
        self._healthy = HealthyCalls(type(self).__name__, self._distributed, system.stats)
        # Plain attributes, not submodules: a twin is no part of the model's state_dict (__setattr__).
        #: ``route``: the layer that answers this layer's calls instead of it (:mod:`fempdl.layer.reference`);
        #: ``reference_twin``: the converged twin that answers them at reference physics (built on first use).
        self.__dict__.update(route=None, reference_twin=None)
        #: Calls without gradients at a cap (a validation computed with capped physics), counted for PRDP.
        self.capped_eval_calls = 0
        self._mover = _nobody             # a weak reference to the PRDP moving this layer (moved_by)

    def __setattr__(self, name: str, value) -> None:
        if name in ("route", "reference_twin"):       # torch would register a Module value as a submodule
            self.__dict__[name] = value
        else:
            super().__setattr__(name, value)

    @property
    def reference_stats(self):
        """The counters of this layer's solves at reference physics (:mod:`fempdl.layer.reference`), kept
        apart from :attr:`stats`; None before the first."""
        return None if self.reference_twin is None else self.reference_twin.stats

    def acting(self) -> SystemLayer:
        """The layer that solves this layer's calls now: itself, or the twin it is routed to."""
        return self if self.route is None else self.route

    def note_call(self, training: bool) -> None:
        """Count a call made without gradients at a cap (what a capped validation looks like)."""
        if not training and self.capped:
            self.capped_eval_calls += 1

    @property
    def capped(self) -> bool:
        """Whether a solve of this layer stops at a cap rather than at convergence."""
        options = self.options
        inner = getattr(options, "ksp", None)            # a Newton layer's inner solve
        if inner is not None:
            return options.max_it is not None or (inner.max_it is not None and not inner.direct)
        return options.max_it is not None and not options.direct

    @property
    def health(self) -> HealthCheck | None:
        """The rule for garbage capped solves (:mod:`fempdl.solve.health`), ``None`` for none. PRDP installs
        one on the layers it moves (``PRDPSettings.health``); setting it makes the system measure the
        residual ratio of its capped forward solves and of their adjoint solves."""
        return self._healthy.check

    @health.setter
    def health(self, check: HealthCheck | None) -> None:
        self._healthy.install(check)

    @property
    def health_schedule(self) -> dict:
        """When the health check measures the next training calls (:meth:`HealthyCalls.schedule
        <fempdl.layer.healthy_calls.HealthyCalls.schedule>`); assign a saved one to resume it."""
        return self._healthy.schedule()

    @health_schedule.setter
    def health_schedule(self, saved: dict) -> None:
        self._healthy.load_schedule(saved)

    @property
    def last_health_ratio(self) -> float | None:
        """The largest residual ratio of the last training call the health check measured (None: none yet)."""
        return self._healthy.last_ratio["forward"]

    @property
    def last_adjoint_health_ratio(self) -> float | None:
        """The same for the adjoint solves of the last backward measured."""
        return self._healthy.last_ratio["adjoint"]

    def solve_healthy(self, solve: Callable[[CallHealth | None], object], training: bool,
                      direction: str = "forward", exact: bool | None = None):
        """``solve(health)``, one call's capped solves (a forward, or its backward's adjoint solves), run
        again at a refined cap while garbage (:class:`~fempdl.layer.healthy_calls.HealthyCalls`); ``exact``:
        whether this call's gradient is the physics' derivative to the capped map's (default
        :attr:`exact_capped_gradient`)."""
        exact = self.exact_capped_gradient if exact is None else exact
        return self._healthy.run(solve, lambda: self.caps, training, direction, exact=exact,
                                 watched=self._stationary_cap())

    @property
    def options(self):
        return self.system.options

    @property
    def max_it(self) -> int | None:
        return self.system.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        self.system.max_it = value

    #: Whether this layer's own cap (``caps.max_it``) counts Newton steps rather than Krylov iterations.
    counts_newton_steps = False

    def _stationary_cap(self) -> bool:
        """Whether a plain call's solves are watched for a growing residual (:mod:`~fempdl.layer.healthy_calls`):
        a capped stationary iteration's (a linear layer's)."""
        return False

    #: Whether the health check measures the adjoint solves of this layer's backward too (a linear system's).
    measures_adjoint_health = False

    @property
    def exact_capped_gradient(self) -> bool:
        """Whether the backward is the exact derivative of the capped map that ran (unrolled, or Richardson +
        Jacobi with right-hand-side controls only), rather than the implicit-function approximation at an
        unconverged state, wrong by about the state's and the adjoint's error."""
        if self.diff == "unrolled":
            return True
        options = self.options
        return (not self.counts_newton_steps and options.ksp_type == "richardson" and options.pc_type == "jacobi"
                and not self.problem.matrix_controls)

    @property
    def caps(self) -> Caps:
        """This layer's caps as one value (:mod:`fempdl.solve.caps`); assign a :class:`Caps` to move them."""
        return self.system.caps

    @caps.setter
    def caps(self, caps: Caps) -> None:
        if not isinstance(caps, Caps):
            raise TypeError(f"caps must be a fempdl.Caps, got {type(caps).__name__}; or set max_it")
        if caps != self.system.caps:
            self._check_caps(caps)
            self.system.caps = caps

    def _check_caps(self, caps: Caps) -> None:
        """Refuse caps this layer cannot solve at, before any cap moves (a Newton layer checks both)."""

    def moved_by(self, controller) -> None:
        """Make ``controller`` (a PRDP, held weakly; ``None``: none) what moves this layer's caps. Its record
        (``controller.steps_record``: steps, last metric, k_cap) is what the ranks of a torch.distributed group
        agree on with the caps at each training call (:meth:`_check_caps_over_torch_group`)."""
        self._mover = _nobody if controller is None else weakref.ref(controller)

    def _prdp_record(self) -> tuple:
        controller = self._mover()
        return (0, None, None) if controller is None else controller.steps_record

    def as_target(self) -> LayerCaps:
        """What PRDP moves on this layer (:mod:`fempdl.layer.cap_target`): its own cap, ``caps.max_it``."""
        return LayerCaps((self,), call=self)

    @property
    def system(self):
        """The assembled system (raises once the layer is closed)."""
        if self._system is None:
            kind = type(self).__name__
            raise RuntimeError(f"this {kind} was closed (close() freed its PETSc objects); "
                               f"create a new {kind} to solve again")
        return self._system

    @property
    def stats(self) -> CumulativeStats:
        """Cumulative counters of every solve of this layer."""
        return self.system.stats

    def _inputs(self, positional, initial_guess, controls: dict):
        """Checked call inputs: (names, tensors, batch, batched, dtype, device), the ranks' calls compared."""
        if positional:
            names = [n for n in self.problem.control_names]
            raise TypeError(f"{type(self).__name__} takes its controls as keywords, got {len(positional)} positional "
                            f"argument(s); call it as layer({', '.join(f'{n}=...' for n in names)})")
        if initial_guess is not None:
            controls = {**controls, INITIAL_GUESS: initial_guess}
        networks = self.problem.networks
        if networks:
            given = sorted(set(controls) & set(networks))
            if given:
                raise ValueError(f"{given} name the problem's network(s), whose parameters the layer passes itself "
                                 "(the module's current weights, by value); call the layer with its controls only")
            controls = {**controls, **{n: network.parameters_tensor() for n, network in networks.items()}}
        names, tensors, batch, batched = self._validate(controls)
        self.note_call(torch.is_grad_enabled() and any(t.requires_grad for t in tensors))
        if self._distributed:
            self._check_ranks_agree(names, tensors, batch)
        elif torch_group_initialised() and torch.is_grad_enabled() and any(t.requires_grad for t in tensors):
            self._check_caps_over_torch_group()
        self.problem.check_constants()         # after the ranks agree on them: a refusal on every rank or none
        dtype = tensors[0].dtype if tensors else torch.float64
        if any(t.dtype != dtype for t in tensors):
            dtype = torch.float64
        device = tensors[0].device if tensors else torch.device("cpu")
        return names, tensors, batch, batched, dtype, device

    def _implicit(self, names, tensors, batch: int, dtype) -> torch.Tensor:
        """The solve as one opaque operator whose backward is the system's adjoint."""
        # The operator checks the controls for NaN/inf and the float32 range of the solution.
        keep = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
        return ImplicitSolve.apply(self._handle, names, batch, keep, dtype != torch.float64, *tensors)[0]

    def call_signature(self, names, tensors, batch: int) -> dict:
        """What every rank's call of this layer on a distributed mesh must share (the solves are collective,
        and the dtype, a control's sharing and the grad mode choose which collectives run; the Constants
        are the physics: ranks at different dt would each assemble their rows of a different operator)."""
        return {"caps": self.caps, "batch": batch, "controls": tuple(names),
                "dtypes": tuple(str(t.dtype).removeprefix("torch.") for t in tensors),
                "shared (n,) or batched (B, n)": tuple("shared" if t.dim() == 1 else "batched" for t in tensors),
                "requires_grad": tuple(t.requires_grad for t in tensors) if torch.is_grad_enabled() else "no_grad",
                "Constants": tuple((name, tuple(np.ravel(c.value).tolist()))
                                   for name, c in self.problem.constants.items()),
                # The weights are every rank's: ranks holding different ones would assemble different physics.
                "network weights": tuple(hashlib.sha1(t.detach().cpu().numpy().tobytes()).hexdigest()[:16]
                                         for n, t in zip(names, tensors) if n in self.problem.networks)}

    def _check_ranks_agree(self, names, tensors, batch: int, extra: dict | None = None, caller: str = "") -> None:
        """On a distributed mesh every rank must make the same call (:meth:`call_signature`, with ``extra``
        entries of a caller's own): one allgather of it, and a ValueError on every rank if they differ,
        instead of ranks waiting in different collectives (a hang) or solving different physics."""
        comm = self.problem.V.mesh.comm
        mine = {**self.call_signature(names, tensors, batch), **(extra or {})}
        every = comm.allgather(mine)
        # Compared as text: a NaN Constant equal on every rank is no disagreement (the finite check names it).
        differ = [key for key in mine if any(repr(call[key]) != repr(mine[key]) for call in every)]
        if differ:
            by_rank = "; ".join(f"{key}: {[call[key] for call in every]}" for key in differ)
            what = caller or f"this distributed-mesh {type(self).__name__}"
            hint = (". A PRDP step on per-rank metrics moves the caps apart: step PRDP with the same (reduced) "
                    "metric on every rank") if "caps" in differ else ""
            raise ValueError(f"the ranks called {what} differently ({by_rank}, by rank); every rank must call it "
                             f"with the same {', '.join(differ)}{hint}")

    def _check_caps_over_torch_group(self) -> None:
        """Under torch.distributed (torchrun + DDP) each process holds the whole mesh, so no solve is
        collective and ranks whose caps drift apart would train on different physics with equal
        parameters, silently. A training call (gradients enabled) is collective under DDP anyway, so one
        all-reduce of the caps there cannot hang a loop that validates on rank 0 alone."""
        ranks = training_ranks()
        mine, record = self.caps, self._prdp_record()
        if ranks is None or ranks.agree((mine.max_it, mine.inner_max_it, *record)):
            return
        every = ranks.allgather((mine, record))
        steps, metrics, k_caps = ([record[i] for _, record in every] for i in range(3))
        if len(set(steps)) > 1:
            raise ValueError(
                f"PRDP.step ran on some ranks of the torch.distributed group only (steps by rank: {steps}); a step "
                "on one rank moves its caps alone. Call ctrl.step on every rank with the same metric: validate on "
                "rank 0 and share the value (torch.distributed.broadcast_object_list), or all-reduce the sums it "
                "is made of")
        if len(set(metrics)) > 1:
            raise ValueError(different_metrics_message(metrics, ranks))
        if len(set(k_caps)) > 1:
            raise ValueError(
                f"PRDP measured K_eps again to different k_caps on the ranks ({k_caps}, by rank); validate on the "
                "same data on every rank (an all-reduced metric) so that the measurement agrees")
        every = [caps for caps, _ in every]
        if any(caps != mine for caps in every):
            raise ValueError(
                f"the ranks of the torch.distributed group train this {type(self).__name__} at different caps "
                f"({every}, by rank); every rank must train at the same caps: step PRDP on every rank with the "
                "same (all-reduced) metric, or set max_it on every rank")

    def _check_finite(self, names, tensors) -> None:
        for name, t in zip(names, tensors):
            bad = count_on_all_ranks(~torch.isfinite(t.detach()), self.problem)
            if bad:
                raise ValueError(nonfinite_control_message(name, bad))
            self.problem.check_control_values(name, t)

    def _report_overflow(self, dtype) -> None:
        message = (f"the solution is finite in float64 but overflows {dtype}; pass float64 controls "
                   "or rescale the problem")
        if self.options.on_failure == "warn":
            warn_at_caller(message, RuntimeWarning)
        else:
            raise OverflowError(message)

    def get_extra_state(self) -> dict:
        """The caps travel with ``state_dict()``: a saved model reloads at the K it was trained at."""
        return dataclasses.asdict(self.caps)

    def set_extra_state(self, state: dict) -> None:
        if not isinstance(state, dict) or "max_it" not in state:
            raise ValueError(f"{type(self).__name__} state must be a dict with 'max_it', got {state!r}")
        self.caps = Caps(state["max_it"], state.get("inner_max_it", self.caps.inner_max_it))

    def __getstate__(self):
        raise TypeError(f"a {type(self).__name__} holds DOLFINx and PETSc objects, which cannot be pickled or "
                        "deep-copied (torch.save(model), copy.deepcopy, AveragedModel); save model.state_dict() "
                        "instead (it carries each layer's max_it) and rebuild the model, with its layers, from its "
                        "Problem")

    def close(self) -> None:
        """Free the PETSc objects now (otherwise when the system is garbage collected: a system still
        referenced, ``SolveLayer(p).system``, outlives its layer)."""
        if getattr(self, "_system", None) is not None:
            self._system.destroy()
            self._system = None
        if self.__dict__.get("reference_twin") is not None:
            self.reference_twin.close()
            self.reference_twin = None

    def _validate(self, controls: dict):
        sizes = self._sizes
        unknown = [n for n in controls if n not in sizes]
        if unknown:
            raise ValueError(f"unknown control(s) {unknown}; this layer's controls are "
                             f"{list(self.problem.control_names)}")
        names = tuple(n for n in sizes if n in controls)
        tensors = [controls[n] for n in names]
        batch_sizes = {}
        for name, t in zip(names, tensors):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"control {name!r} must be a torch.Tensor, got {type(t).__name__}; "
                                "wrap arrays with torch.as_tensor(..., dtype=torch.float64)")
            if t.dtype not in _FLOAT_DTYPES:
                raise TypeError(f"control {name!r} has dtype {t.dtype}; use float32 or float64 "
                                "(e.g. tensor.double())")
            n = sizes[name]
            if t.dim() not in (1, 2) or t.shape[-1] != n:
                raise ValueError(
                    f"control {name!r} has shape {tuple(t.shape)}, expected (B, {n}) or ({n},): one value per "
                    f"owned DOF of its space; a different size usually means a tensor built for another "
                    f"mesh, space or degree (see problem.control_size({name!r}))")
            if t.dim() == 2:
                if t.shape[0] == 0:
                    raise ValueError(f"control {name!r} has an empty batch (shape {tuple(t.shape)})")
                batch_sizes[name] = t.shape[0]
        if len(set(batch_sizes.values())) > 1:
            raise ValueError(f"controls have different batch sizes {batch_sizes}; "
                             "pass (B, n) tensors with one B, or (n,) tensors shared by all samples")
        devices = {t.device for t in tensors}
        if len(devices) > 1:
            raise ValueError(f"controls are on different devices {sorted(map(str, devices))}; move them to one")
        batch = next(iter(batch_sizes.values()), 1)
        return names, tensors, batch, bool(batch_sizes)
