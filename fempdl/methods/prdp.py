"""PRDP: raise a solver's iteration cap K only when the validation metric plateaus.

The controller of "Progressively Refined Differentiable Physics" (Algorithm 4).
After every validation, :meth:`PRDP.step` takes the metric (lower is better):
it smooths the history with an EMA, and when the progress over the last
``delta`` entries stalls (ratio above ``tau_step``) it refines K by ``dk``
(never above ``k_cap``) unless the previous refinement bought less than
1 - ``tau_stop`` (then it holds, until the metric moves again). The interface
follows ``ReduceLROnPlateau``: ``step(metric) -> bool``, ``state_dict()``.

Between validations, the layers it moves refine at once when a training call's
capped solves are garbage rather than coarse: their residual grew, or did not
shrink below ``health`` times its start (:mod:`fempdl.solve.health`). The layer
solves that call again at the refined cap, so the network never trains on it;
:attr:`PRDP.health_refinements` lists these refinements.

:func:`k_eps` measures a layer's converged cap K_eps, the usual ``k_cap``.
"""
from __future__ import annotations

import dataclasses
import logging
import math
import weakref
from collections.abc import Callable, Iterable

from mpi4py import MPI
import torch

from fempdl.core.checks import check_int
from fempdl.core.parallel import shard_inputs
from fempdl.core.ranks import Ranks, training_ranks
from fempdl.layer.solve_layer import SolveLayer
from fempdl.layer.system_layer import SystemLayer
from fempdl.solve.health import HealthCheck

__all__ = ["PRDP", "PRDPRecord", "PRDPSettings", "k_eps"]
_log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class PRDPRecord:
    """One call of :meth:`PRDP.step`: the K in force while ``metric`` was
    measured, the smoothed metric, the ratios (None before a decision is
    possible or when not computed) and whether K was raised afterwards."""

    step: int
    k: int
    metric: float
    ema: float
    r: float | None
    rc: float | None
    refined: bool
    cause: str | None = None      # "plateau" or "rise" (the guard) when refined


def _setting(default, doc: str, kind: type, **bounds):
    """A field of :class:`PRDPSettings`; its metadata (kind, doc, bounds) is what scene files are checked
    against (``[prdp]`` of :mod:`fempdl.app.schema`)."""
    return dataclasses.field(default=default, metadata={"kind": kind, "doc": doc, **bounds})


_POSITIVE = 1e-300      # a minimum of "> 0"


@dataclasses.dataclass(frozen=True, kw_only=True)
class PRDPSettings:
    """The settings of a :class:`PRDP` controller, validated once (change one with
    :func:`dataclasses.replace`). They are also the ``[prdp]`` section of a scene file."""

    k0: int = _setting(1, "first cap", int, minimum=1)
    dk: int = _setting(1, "least increase of a refinement", int, minimum=1)
    tau_step: float = _setting(0.95, "refine when the metric improves less than this factor", float,
                               minimum=_POSITIVE, maximum=1.0)
    tau_stop: float = _setting(0.9, "stop refining when a refinement improves less than this factor", float,
                               minimum=_POSITIVE, maximum=1.0)
    delta: int = _setting(3, "epochs compared for a plateau", int, minimum=2)
    ema_window: int = _setting(6, "epochs of the metric's moving average", int, minimum=1)
    k_cap: int | None = _setting(None, "largest cap (none: K_eps in a scene, unbounded in PRDP)", int, minimum=1)
    guard: float | None = _setting(None, "refine at once when the metric rises above guard x its best "
                                         "(none: never)", float, minimum=1.0 + 1e-12)
    growth: float = _setting(1.0, "a refinement sets K to max(K + dk, ceil(growth K))", float, minimum=1.0)
    health: float | None = _setting(1.0, "refine at once when a training call's capped solve ends with its residual "
                                         "above health x its start, and solve it again (none: never)", float,
                                    minimum=_POSITIVE)

    def __post_init__(self):
        check_int("k0", self.k0, minimum=1)
        check_int("dk", self.dk, minimum=1)
        check_int("delta", self.delta, minimum=2)
        check_int("ema_window", self.ema_window, minimum=1)
        if self.k_cap is not None:
            check_int("k_cap", self.k_cap, minimum=self.k0)
        for name in ("tau_step", "tau_stop"):
            value = getattr(self, name)
            if not _is_number(value) or not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be a number in (0, 1], got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.guard is not None:
            if not (_is_number(self.guard) and 1.0 < self.guard < math.inf):
                raise ValueError(f"guard must be a finite number > 1 (or None: off), got {self.guard!r}")
            object.__setattr__(self, "guard", float(self.guard))
        if not (_is_number(self.growth) and 1.0 <= self.growth < math.inf):
            raise ValueError(f"growth must be a finite number >= 1, got {self.growth!r}")
        object.__setattr__(self, "growth", float(self.growth))
        if self.health is not None:
            if not (_is_number(self.health) and 0.0 < self.health < math.inf):
                raise ValueError(f"health must be a finite residual ratio > 0 (or None: off), got {self.health!r}")
            object.__setattr__(self, "health", float(self.health))


_SETTING_NAMES = frozenset(f.name for f in dataclasses.fields(PRDPSettings))


class PRDP:
    """Progressive refinement of an iteration cap K.

    At every :meth:`step`: ema is the EMA of the metrics (alpha =
    2 / (ema_window + 1), ema[0] = m[0]); with more than ``delta`` entries,
    r = ema[-1] / ema[-delta]. If r > tau_step (a plateau), rc = ema[-1] / c
    compares it with the checkpoint c of the previous plateau (c starts at the
    first metric): if rc < tau_stop (the last refinement still helped) or
    rc > 1 (the metric got worse), c = ema[-1] and K is refined; otherwise K
    holds. ``guard`` and ``growth`` are optional departures, off by default.

    Args:
        target: a layer (anything with a ``max_it`` attribute), a list of them,
            a callable ``f(k)``, or ``None`` (read :attr:`k` yourself). Its cap is
            set to ``k0`` at construction.
        settings: a :class:`PRDPSettings`, or none to give its fields as keywords:
        k0: the starting cap (>= 1).
        dk: increment per refinement (>= 1).
        tau_step: plateau threshold on r in (0, 1].
        tau_stop: stagnation threshold on rc in (0, 1].
        delta: grace interval (>= 2): r compares with delta - 1 steps earlier.
        ema_window: EMA window (alpha = 2 / (ema_window + 1)); >= 1.
        k_cap: upper bound for K (``None``: unbounded).
        guard: refine at once when the metric exceeds ``guard`` (> 1) times the
            best metric so far and the previous one (``None``: off).
        growth: a refinement sets K = max(K + dk, ceil(growth * K)) (>= 1; 1: K + dk).
        health: the largest residual ratio ||r_K|| / ||r_0|| of a training call's capped solves
            (:mod:`fempdl.solve.health`) before the target layers refine K at once and solve that call
            again (1, the default: a residual that did not shrink; ``None``: off). Measured on the first
            training call at new caps and every 8th after, at one matrix-vector product per capped linear
            sample (two from a warm start) and nothing for Newton.
        comm: the ranks that train together: an ``mpi4py`` communicator or a
            torch.distributed ``ProcessGroup``. Default: the communicator of the
            target layers' mesh when it is distributed, else torch.distributed's
            default group when one is initialised (torchrun + DDP), else none
            (:func:`fempdl.core.ranks.training_ranks`). With more than one rank,
            :meth:`step` checks that every rank passes the same metric (else a
            rank would refine alone: the collective solves of a distributed mesh
            hang, and data-parallel ranks train on different physics).

    The settings read as attributes too (``ctrl.k_cap``, ``ctrl.tau_step``, ...).
    """

    def __init__(self, target=None, settings: PRDPSettings | None = None, *, comm=None, **fields):
        if settings is None:
            settings = PRDPSettings(**fields)
        elif fields:
            raise TypeError(f"give PRDP either settings= or the settings' fields as keywords, not both "
                            f"(got settings and {sorted(fields)})")
        elif not isinstance(settings, PRDPSettings):
            raise TypeError(f"settings must be PRDPSettings, got {type(settings).__name__}")
        self.settings = settings
        self._apply = _setter(target)
        self._given_comm = comm
        self.comm = comm if comm is not None else _layers_comm(target)
        self.alpha = 2.0 / (settings.ema_window + 1.0)
        self.k = settings.k0
        self.checkpoint: float | None = None
        self.history: list[PRDPRecord] = []
        #: Refinements for garbage solves between validations: dicts of the step (validations so far),
        #: the cap before and after and the residual ratio that asked for it.
        self.health_refinements: list[dict] = []
        self._apply(self.k)
        self._install_health(target)

    def __getattr__(self, name: str):
        if name in _SETTING_NAMES and "settings" in self.__dict__:
            return getattr(self.__dict__["settings"], name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def ema(self) -> list[float]:
        return [rec.ema for rec in self.history]

    def step(self, metric: float) -> bool:
        """Record a validation metric; returns True if K was raised."""
        if isinstance(metric, bool) or not isinstance(metric, (int, float)) and not hasattr(metric, "__float__"):
            raise TypeError(f"metric must be a number, got {type(metric).__name__}")
        metric = float(metric)
        self._check_ranks_agree(metric)
        if not math.isfinite(metric) or metric <= 0.0:
            raise ValueError(f"metric must be finite and > 0 (a validation error), got {metric!r}")
        ema = metric if not self.history else self.alpha * metric + (1.0 - self.alpha) * self.history[-1].ema
        if self.checkpoint is None:
            self.checkpoint = metric
        k_used = self.k
        r = rc = None
        cause = None
        if self.guard is not None and self.history and metric > self.history[-1].metric \
                and metric > self.guard * min(rec.metric for rec in self.history):
            cause = "rise"
            self.checkpoint = ema
        elif len(self.history) + 1 > self.delta:
            emas = self.ema + [ema]
            r = emas[-1] / emas[-self.delta]
            if r > self.tau_step:
                rc = emas[-1] / self.checkpoint
                if rc < self.tau_stop or rc > 1.0:
                    self.checkpoint = emas[-1]
                    cause = "plateau"
        refine = cause is not None and self._can_refine()
        self.history.append(PRDPRecord(step=len(self.history), k=k_used, metric=metric, ema=ema,
                                       r=r, rc=rc, refined=refine, cause=cause if refine else None))
        if refine:
            self._refine()
            _log.info("PRDP: K %d -> %d (%s) at step %d, metric %.3e", k_used, self.k, cause,
                      len(self.history) - 1, metric)
        return refine

    def _can_refine(self) -> bool:
        return self.k_cap is None or self.k < self.k_cap

    def _refine(self) -> None:
        k = max(self.k + self.dk, math.ceil(self.growth * self.k - 1e-9))
        self.k = k if self.k_cap is None else min(k, self.k_cap)
        self._apply(self.k)

    def refine_for_health(self, ratio: float) -> bool:
        """Refine K now, for a training call whose capped solves ended with residual ratio ``ratio``
        (a layer's :class:`~fempdl.solve.health.HealthCheck` calls it); False when K is at ``k_cap``."""
        if not self._can_refine():
            return False
        k_used = self.k
        self._refine()
        self.health_refinements.append({"step": len(self.history), "k": k_used, "to": self.k, "ratio": float(ratio)})
        _log.info("PRDP: K %d -> %d (a capped solve's residual ended at %.3g x its start) before step %d",
                  k_used, self.k, ratio, len(self.history))
        return True

    def _install_health(self, target) -> None:
        """Give the target's layers the health check (``health`` set), or take a previous one away."""
        layers = [layer for t in _targets(target) for layer in getattr(t, "layers", [t])
                  if isinstance(layer, SystemLayer)]
        if self.health is None:
            for layer in layers:
                layer.health = None
            return
        refine = weakref.WeakMethod(self.refine_for_health)    # the layers do not keep the controller alive
        check = HealthCheck(self.health, lambda ratio: (refine() or _cannot_refine)(ratio))
        for layer in layers:
            layer.health = check

    @property
    def ranks(self) -> Ranks | None:
        """The ranks whose metrics must agree (looked up at each step: a torch.distributed group may
        be initialised after the controller was built)."""
        return training_ranks(self._given_comm, self.comm)

    def _check_ranks_agree(self, metric: float) -> None:
        ranks = self.ranks
        if ranks is None or ranks.size == 1 or ranks.agree((metric,)):
            return
        every = ranks.allgather(metric)
        if any(m != metric for m in every):
            reduce = ("torch.distributed.all_reduce(total) on the sums and counts the metric is made of"
                      if ranks.kind.startswith("torch") else "comm.allreduce(error_sum) / comm.allreduce(count)")
            raise ValueError(
                f"PRDP.step got different metrics on the {ranks.size} ranks ({every}) of its {ranks.kind}; every "
                "rank must step with the same metric, or one rank refines K alone (the collective solves of a "
                f"distributed mesh hang; data-parallel ranks train on different physics): reduce it first, e.g. "
                f"{reduce}")

    def state_dict(self) -> dict:
        """Everything needed to continue: K, the checkpoint, the history and the settings."""
        return {
            "k": self.k, "checkpoint": self.checkpoint,
            "history": [dataclasses.asdict(rec) for rec in self.history],
            "health_refinements": [dict(event) for event in self.health_refinements],
            "settings": dataclasses.asdict(self.settings),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from :meth:`state_dict` (and set the target's cap to the saved K)."""
        # States saved before guard and growth existed ran plain Algorithm 4; health acts between
        # validations and leaves the saved history valid, so a state saved before it resumes with either.
        settings = {"guard": None, "growth": 1.0, "health": self.health, **state["settings"]}
        mine = self.state_dict()["settings"]
        if settings != mine:
            changed = {k: (settings.get(k), v) for k, v in mine.items() if settings.get(k) != v}
            raise ValueError(f"saved PRDP settings differ from this controller's (saved, current): {changed}")
        self.k = int(state["k"])
        self.checkpoint = state["checkpoint"]
        self.history = [PRDPRecord(**rec) for rec in state["history"]]
        self.health_refinements = [dict(event) for event in state.get("health_refinements", [])]
        self._apply(self.k)

    def __repr__(self) -> str:
        settings = ", ".join(f"{key}={value}" for key, value in dataclasses.asdict(self.settings).items())
        return f"PRDP(k={self.k}, {settings}, steps={len(self.history)})"


def k_eps(layer: SolveLayer, *, rtol: float = 1e-8, shard_over: MPI.Comm = MPI.COMM_SELF,
          batch: int | None = None, **controls) -> int:
    """K_eps: the most iterations ``layer``'s solver needs to reach ``rtol`` on
    ``controls`` (the layer's keyword inputs, (B, n) or (n,), e.g. validation
    samples), found by converged solves of a probe layer with the same
    solver and preconditioner (PETSc; ``layer`` itself and its counters are
    left as they are). Use it as PRDP's ``k_cap``.

    ``shard_over``: the samples are spread over its ranks (data-parallel training, every rank
    holding the whole problem; all of them call) and K_eps is the maximum over the ranks.
    ``batch``: probe in calls of that many samples, as training calls the layer (a lagged
    preconditioner is set up once a call); ``None``: one call.

    Example:
        ``ctrl = PRDP(layer, k0=1, dk=1, k_cap=k_eps(layer, f=f_val, rtol=1e-6))``
    """
    if not isinstance(layer, SolveLayer):
        raise TypeError(f"layer must be a SolveLayer, got {type(layer).__name__}")
    if not controls:
        raise ValueError(f"give the inputs to measure K_eps on as keyword arguments, e.g. "
                         f"{layer.problem.control_names[0] if layer.problem.control_names else 'f'}=tensor")
    if layer.options.direct:
        raise ValueError(f"layer solves directly (ksp_type={layer.options.ksp_type!r}): it has no iteration cap")
    options = dataclasses.replace(layer.options, max_it=None, rtol=rtol, atol=None, divtol=None, adjoint=None,
                                  engine="petsc", options_prefix=None)
    mine = shard_inputs(controls, shard_over)
    samples = next(iter(mine.values())).shape[0]
    probe = SolveLayer(layer.problem, options)
    try:
        with torch.no_grad():
            for start in range(0, samples, batch or max(samples, 1)):
                probe(**{name: value[start:start + (batch or samples)] for name, value in mine.items()})
        most = probe.stats.max_forward_iterations
    finally:
        probe.close()
    return shard_over.allreduce(most, op=MPI.MAX)


def _layers_comm(target):
    """The communicator of the first target layer's mesh (``None`` for other targets)."""
    for t in _targets(target):
        problem = getattr(t, "problem", None)
        if problem is not None:
            return problem.V.mesh.comm
    return None


def _targets(target) -> list:
    """The objects with a ``max_it`` that ``target`` names (none for None or a callable)."""
    if target is None or callable(target) and not hasattr(target, "max_it"):
        return []
    return list(target) if isinstance(target, Iterable) and not hasattr(target, "max_it") else [target]


def _cannot_refine(ratio: float) -> bool:
    """The health check of a controller that no longer exists."""
    return False


def _setter(target) -> Callable[[int], None]:
    if target is None:
        return lambda k: None
    if callable(target) and not hasattr(target, "max_it"):
        return target
    targets = _targets(target)
    for i, t in enumerate(targets):
        if not hasattr(t, "max_it"):
            raise TypeError(f"PRDP target {i} ({type(t).__name__}) has no max_it attribute; pass SolveLayers, "
                            "a callable f(k), or None")

    def apply(k: int) -> None:
        for t in targets:
            t.max_it = k
    return apply


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)
