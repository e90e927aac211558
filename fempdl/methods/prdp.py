"""PRDP: raise a solver's iteration cap K only when the validation metric plateaus.

The controller of "Progressively Refined Differentiable Physics" (Algorithm 4).
After every validation, :meth:`PRDP.step` takes the metric (lower is better):
it smooths the history with an EMA, and when the progress over the last
``delta`` entries stalls (ratio above ``tau_step``) it refines K by ``dk``
(never above ``k_cap``) unless the previous refinement bought less than
1 - ``tau_stop`` (then it holds, until the metric moves again). The interface
follows ``ReduceLROnPlateau``: ``step(metric) -> bool``, ``state_dict()``.

The metric judges the model with the physics it is deployed with. A network
trained through capped solves can learn the cap's bias, which a metric computed
with the same capped solves cannot see; so ``step`` takes the validation as a
function and runs it at reference physics (converged solves,
:mod:`fempdl.layer.reference`; ``judge="capped"`` for a model deployed capped).
Where the rule would hold, or K sits at ``k_cap``, on a plateau, it also runs the
validation at the caps: while the two metrics differ by more than ``gap`` (the
network leans on the cap, or the cap still moves what the model is judged at)
K is refined (cause ``"gap"``); at ``k_cap`` K_eps is measured again at the
current model (``remeasure``) and ``k_cap`` raised to it (cause ``"k_eps"``).
A metric given as a number is taken as it is; if the layers were called capped
without gradients since the last step (a capped validation), PRDP warns once.

Between validations, the layers it moves refine at once when a training call's
capped solves are garbage rather than coarse: their residual grew, or did not
shrink below ``health`` times its start (:mod:`fempdl.solve.health`). The layer
solves that call again at the refined cap, so the network never trains on it;
:attr:`PRDP.health_refinements` lists these refinements.

:func:`~fempdl.methods.k_eps.k_eps` measures the converged cap K_eps, the usual ``k_cap``.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import warnings
import weakref
from collections.abc import Callable

import torch

from fempdl.core.ranks import Ranks, different_metrics_message, training_ranks
from fempdl.layer.cap_target import CapTarget, as_target
from fempdl.layer.reference import reference_physics
from fempdl.methods.k_eps import k_eps
from fempdl.methods.prdp_settings import SETTING_NAMES, PRDPRecord, PRDPSettings
from fempdl.solve.health import HealthCheck

__all__ = ["PRDP", "PRDPRecord", "PRDPSettings", "PRDPValidationWarning", "k_eps"]
_log = logging.getLogger(__name__)


class PRDPValidationWarning(UserWarning):
    """PRDP was stepped with a metric computed with capped solves (module docstring)."""


class PRDP:
    """Progressive refinement of an iteration cap K.

    At every :meth:`step`: ema is the EMA of the metrics (alpha =
    2 / (ema_window + 1), ema[0] = m[0]); with more than ``delta`` entries,
    r = ema[-1] / ema[-delta]. If r > tau_step (a plateau), rc = ema[-1] / c
    compares it with the checkpoint c of the previous plateau (c starts at the
    first metric): if rc < tau_stop (the last refinement still helped) or
    rc > 1 (the metric got worse), c = ema[-1] and K is refined; otherwise K
    holds. ``guard`` and ``growth`` are optional departures, off by default.
    Where the rule holds, or K is at ``k_cap``, on a plateau, a metric given as a
    function is also run at the caps, and K refined while the two differ by more
    than ``gap`` (|capped - reference| / the smaller; module docstring).

    Args:
        target: what K moves (:func:`fempdl.layer.cap_target.as_target`): a solve layer, a
            :class:`~fempdl.methods.newton_caps.NewtonCaps`, a Rollout, an object with a ``max_it``
            attribute, a list of them, a callable ``f(k)``, or ``None`` (read :attr:`k` yourself).
            Its cap is set to ``k0`` at construction.
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
        judge: ``"reference"`` (a metric given as a function runs at converged physics) or
            ``"capped"`` (at the caps: a model deployed with the capped solver; no gap rule).
        gap: the largest relative difference |capped - reference| / min(capped, reference) at which the rule may
            hold or stop at ``k_cap`` (``None``: never checked).
        remeasure: at ``k_cap`` with the gap open, measure K_eps at the current model (to
            ``k_eps_rtol``) and raise ``k_cap`` to it.
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
        self._target = target = as_target(target)
        self._given_comm = comm
        self.comm = comm if comm is not None else _layers_comm(target)
        self.alpha = 2.0 / (settings.ema_window + 1.0)
        self.k = settings.k0
        self._k_cap = settings.k_cap
        self._warned = False
        self._gap_closed_at: tuple | None = None
        self._eval_calls = self._capped_eval_calls()
        self.checkpoint: float | None = None
        self.history: list[PRDPRecord] = []
        #: Refinements for garbage solves between validations: dicts of the step (validations so far),
        #: the cap before and after and the residual ratio that asked for it.
        self.health_refinements: list[dict] = []
        target.set_k(self.k)
        self._install_on(target)

    def __getattr__(self, name: str):
        if name in SETTING_NAMES and "settings" in self.__dict__:
            return getattr(self.__dict__["settings"], name)
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")

    @property
    def ema(self) -> list[float]:
        return [rec.ema for rec in self.history]

    @property
    def k_cap(self) -> int | None:
        """The upper bound of K: ``settings.k_cap``, raised where K_eps was measured again."""
        return self._k_cap

    @property
    def layers(self) -> list:
        """The solve layers whose caps PRDP moves."""
        return list(self._target.layers)

    def reference(self):
        """A context in which the layers PRDP moves solve at reference physics (converged; their
        ``reference_stats`` count it): ``with torch.no_grad(), ctrl.reference(): metric = ...``."""
        layers = self.layers
        if not layers:
            raise TypeError("PRDP's target moves no solve layers to run at reference "
                            "physics; compute the metric with converged solves yourself and pass it as a number")
        return reference_physics(layers)

    def step(self, metric, *, capped: float | None = None) -> bool:
        """Record a validation metric; returns True if K was raised.

        Args:
            metric: a function computing the validation metric through the layers PRDP moves (run without
                gradients at reference physics, or at the caps under ``judge="capped"``), or its value.
            capped: with a metric given as a number computed at reference physics, the same metric at the
                caps (for the gap rule); a function's is measured when needed.
        """
        validate = metric if callable(metric) else None
        if validate is not None:
            metric = self._run(validate, at_reference=self.judge == "reference")
        else:
            self._warn_if_validated_capped()
        metric = self._checked(metric, "metric")
        ema = metric if not self.history else self.alpha * metric + (1.0 - self.alpha) * self.history[-1].ema
        if self.checkpoint is None:
            self.checkpoint = metric
        k_used = self.k
        r = rc = gap = None
        cause = None
        plateau = False
        if self.guard is not None and self.history and metric > self.history[-1].metric \
                and metric > self.guard * min(rec.metric for rec in self.history):
            cause = "rise"
            self.checkpoint = ema
        elif len(self.history) + 1 > self.delta:
            emas = self.ema + [ema]
            r = emas[-1] / emas[-self.delta]
            plateau = r > self.tau_step
            if plateau:
                rc = emas[-1] / self.checkpoint
                if rc < self.tau_stop or rc > 1.0:
                    self.checkpoint = emas[-1]
                    cause = "plateau"
        # At k_cap a gap found closed stays closed until k_cap moves: no capped validation at every plateau.
        closed = not self._can_refine() and self._gap_closed_at == (self.k, self.k_cap)
        if plateau and (cause is None or not self._can_refine()) and self.gap is not None and not closed \
                and self.judge == "reference" and (capped is not None or validate is not None):
            capped = self._checked(self._run(validate, at_reference=False) if capped is None else capped,
                                   "capped")
            gap = abs(capped - metric) / min(capped, metric)
            if gap <= self.gap and not self._can_refine():
                self._gap_closed_at = (self.k, self.k_cap)
            if gap > self.gap:
                if self._can_refine():
                    cause = "gap"
                elif self.remeasure and validate is not None and self._raise_k_cap(validate):
                    cause = "k_eps"
                if cause in ("gap", "k_eps"):
                    self.checkpoint = ema
        refine = cause is not None and self._can_refine()
        self.history.append(PRDPRecord(step=len(self.history), k=k_used, metric=metric, ema=ema, r=r, rc=rc,
                                       refined=refine, cause=cause if refine else None,
                                       capped_metric=None if gap is None else capped, gap=gap, k_cap=self.k_cap))
        if refine:
            self._refine()
            _log.info("PRDP: K %d -> %d (%s) at step %d, metric %.3e", k_used, self.k, cause,
                      len(self.history) - 1, metric)
        self._eval_calls = self._capped_eval_calls()
        return refine

    @property
    def steps_record(self) -> tuple:
        """(steps, last metric, k_cap): what the ranks of a torch.distributed group must agree on, which the
        layers PRDP moves read at each training call (:meth:`SystemLayer.moved_by
        <fempdl.layer.system_layer.SystemLayer.moved_by>`)."""
        return len(self.history), (self.history[-1].metric if self.history else None), self.k_cap

    def _run(self, validate: Callable, at_reference: bool) -> float:
        """The metric ``validate()`` computes, without gradients, at reference physics or at the caps."""
        with torch.no_grad(), (self.reference() if at_reference else contextlib.nullcontext()):
            value = validate()
        return value

    def _checked(self, metric, what: str) -> float:
        if isinstance(metric, bool) or not isinstance(metric, (int, float)) and not hasattr(metric, "__float__"):
            raise TypeError(f"{what} must be a number (or a function returning one), got {type(metric).__name__}")
        metric = float(metric)
        self._check_ranks_agree(metric)
        if not math.isfinite(metric) or metric <= 0.0:
            raise ValueError(f"{what} must be finite and > 0 (a validation error), got {metric!r}")
        return metric

    def _capped_eval_calls(self) -> int:
        return sum(layer.capped_eval_calls for layer in self.layers)

    def _warn_if_validated_capped(self) -> None:
        if self._warned or self.judge != "reference" or self._capped_eval_calls() == self._eval_calls:
            return
        self._warned = True
        warnings.warn(
            "the layers PRDP moves were called capped without gradients since the last step: if that was the "
            "validation, its metric cannot see a network that leans on the cap's bias, and PRDP may stop where "
            "converged physics judges the model far worse. Pass the validation as a function, ctrl.step(validate), "
            "and PRDP runs it at reference physics and refines while the capped metric differs; or compute it "
            "inside `with torch.no_grad(), ctrl.reference():`. A model deployed with the capped solver: "
            "PRDP(..., judge='capped')", PRDPValidationWarning, stacklevel=3)

    def _raise_k_cap(self, validate: Callable) -> bool:
        """Measure K_eps on the validation at the current model; raise ``k_cap`` if it lies above."""
        measured = k_eps(self._target, call=validate, rtol=self.k_eps_rtol)
        ranks = self.ranks
        # The largest over the ranks, which may each validate a shard: a measurement runs the validation
        # function, which every rank calls (a step made on one rank alone passes a number, and never
        # measures).
        if ranks is not None and ranks.size > 1:
            measured = int(ranks.max(float(measured)))
        if measured <= self.k_cap:
            return False
        _log.info("PRDP: K_eps measured again at step %d: %d (k_cap was %d)", len(self.history), measured,
                  self.k_cap)
        self._k_cap = measured
        return True

    def _can_refine(self) -> bool:
        return self.k_cap is None or self.k < self.k_cap

    def _refine(self) -> None:
        k = max(self.k + self.dk, math.ceil(self.growth * self.k - 1e-9))
        self.k = k if self.k_cap is None else min(k, self.k_cap)
        self._target.set_k(self.k)

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

    def _install_on(self, target: CapTarget) -> None:
        """Make this controller what moves the target's layers (:meth:`SystemLayer.moved_by
        <fempdl.layer.system_layer.SystemLayer.moved_by>`), and give them the health check (``health`` set)
        or take a previous one away."""
        layers = target.layers
        for layer in layers:
            layer.moved_by(self)
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
        """Over an MPI communicator, now (its ranks step in lockstep). Over a torch.distributed group, at the
        layers' next training call (:attr:`steps_record`):
        validating and stepping on rank 0 alone is a common DDP pattern, and a collective here would wait
        for ranks that never come while they wait in DDP's all-reduce (a hang); a training call is
        collective under DDP anyway, so every rank gets the refusal there."""
        ranks = self.ranks
        if ranks is None or ranks.size == 1 or ranks.torch_group or ranks.agree((metric,)):
            return
        every = ranks.allgather(metric)
        if any(m != metric for m in every):
            raise ValueError(different_metrics_message(every, ranks))

    def state_dict(self) -> dict:
        """Everything needed to continue: K, the checkpoint, the history and the settings."""
        return {
            "k": self.k, "k_cap": self.k_cap, "checkpoint": self.checkpoint,
            "history": [dataclasses.asdict(rec) for rec in self.history],
            "health_refinements": [dict(event) for event in self.health_refinements],
            "settings": dataclasses.asdict(self.settings),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from :meth:`state_dict` (and set the target's cap to the saved K)."""
        # States saved before guard and growth existed ran plain Algorithm 4; health acts between
        # validations and leaves the saved history valid, so a state saved before it resumes with either.
        # The judge, gap and remeasure settings act at the steps to come: a state saved before them resumes too.
        mine = self.state_dict()["settings"]
        later = {key: mine[key] for key in ("judge", "gap", "remeasure", "k_eps_rtol")}
        settings = {"guard": None, "growth": 1.0, "health": self.health, **later, **state["settings"]}
        if settings != mine:
            changed = {k: (settings.get(k), v) for k, v in mine.items() if settings.get(k) != v}
            raise ValueError(f"saved PRDP settings differ from this controller's (saved, current): {changed}")
        self.k = int(state["k"])
        self._k_cap = state.get("k_cap", self.settings.k_cap)
        self.checkpoint = state["checkpoint"]
        self.history = [PRDPRecord(**rec) for rec in state["history"]]
        self.health_refinements = [dict(event) for event in state.get("health_refinements", [])]
        self._target.set_k(self.k)

    def __repr__(self) -> str:
        settings = ", ".join(f"{key}={value}" for key, value in dataclasses.asdict(self.settings).items())
        return f"PRDP(k={self.k}, {settings}, steps={len(self.history)})"


def _layers_comm(target: CapTarget):
    """The communicator of the first target layer's mesh (``None`` for a target without layers)."""
    return target.layers[0].problem.V.mesh.comm if target.layers else None


def _cannot_refine(ratio: float) -> bool:
    """The health check of a controller that no longer exists."""
    return False
