"""PRDP: raise a solver's iteration cap K when the validation metric plateaus, and at once while the cap
changes how the model is judged.

The controller of "Progressively Refined Differentiable Physics" (Algorithm 4),
judged with the physics the model is deployed with: a network trained through
capped solves can learn the cap's bias, which a metric computed with the same
capped solves cannot see. ``step(validate)`` runs the validation function at
reference physics (converged solves, :mod:`fempdl.layer.reference`) and at the
caps, at every step:

* while the two metrics differ by more than ``gap``, K moves at once to the
  cap that closes the gap, found by a doubling search bounded by ``k_cap``
  (cause ``"gap"``, :mod:`fempdl.methods.prdp_gap`); at ``k_cap`` K_eps is
  measured again at the current model and ``k_cap`` raised to it
  (``"k_eps"``);
* otherwise the paper's plateau rule refines K to max(K + dk, ceil(growth K))
  (``"plateau"``; ``"rise"`` for the optional guard).

``finish(validate)``, after the last epoch, closes the gap and returns the
judged metric; it warns where the gap stays open. A metric given as a number is
taken as it is (``capped=`` gives its value at the caps); if the layers were
called capped without gradients since the last step (a capped validation),
PRDP warns once. ``judge="capped"``: a model deployed with the capped solver.

Between validations, the layers it moves refine at once when a training call's
capped solves are garbage rather than coarse: their residual grew, or did not
shrink below ``health`` times its start (:mod:`fempdl.solve.health`). The layer
solves that call again at the refined cap, so the network never trains on it;
:attr:`PRDP.health_refinements` lists these refinements.
"""
from __future__ import annotations

import contextlib
import dataclasses
import logging
import warnings
import weakref
from collections.abc import Callable

import torch

from fempdl.core.ranks import Ranks, refuse_different_metrics, training_ranks
from fempdl.layer.cap_target import CapTarget, as_target
from fempdl.layer.reference import reference_physics
from fempdl.methods.k_eps import k_eps, remeasured_k_eps
from fempdl.methods.prdp_gap import GapSearch, closing_cap, grown_cap, open_gap_message, relative_gap
from fempdl.methods.prdp_settings import (
    SETTING_NAMES,
    PRDPFinish,
    PRDPRecord,
    PRDPSettings,
    check_saved_settings,
    checked_metric,
    refined_cap,
    saved_caps,
)
from fempdl.solve.health import HealthCheck

__all__ = ["PRDP", "PRDPFinish", "PRDPGapWarning", "PRDPRecord", "PRDPSettings", "PRDPValidationWarning", "k_eps"]
_log = logging.getLogger(__name__)


class PRDPValidationWarning(UserWarning):
    """PRDP was stepped with a metric computed with capped solves (module docstring)."""


class PRDPGapWarning(UserWarning):
    """PRDP finished with the capped and the reference metric further apart than ``gap``."""


class PRDP:
    """Progressive refinement of an iteration cap K (module docstring; the rule in docs/api/prdp.md).

    Args:
        target: what K moves (:func:`fempdl.layer.cap_target.as_target`): a solve layer, a
            :class:`~fempdl.methods.newton_caps.NewtonCaps`, a Rollout, an object with a ``max_it``
            attribute, a list of them, a callable ``f(k)``, or ``None`` (read :attr:`k` yourself).
            Its cap is set to ``k0`` at construction.
        settings: a :class:`PRDPSettings` (k0, dk, tau_step, tau_stop, delta, ema_window, k_cap, guard,
            growth, judge, gap, remeasure, k_eps_rtol, health: their meaning is documented there), or none
            to give its fields as keywords.
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
                gradients at reference physics, and at the caps for the gap; at the caps alone under
                ``judge="capped"``), or its value.
            capped: with a metric given as a number computed at reference physics, the same metric at the
                caps (for the gap rule); a function's is measured at every step.
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
        capped = self._capped_metric(validate, capped)
        gap, k_next, probes = None, None, ()
        if capped is not None:
            gap = relative_gap(capped, metric)
            if gap > self.gap:                      # the gap acts first, whatever the plateau rule says
                k_next, probes, gap_cause = self._closing(validate, metric)
                if gap_cause is not None:
                    cause = gap_cause
                    self.checkpoint = ema
            elif not self._can_refine():            # closed at k_cap: not checked again until k_cap moves
                self._gap_closed_at = (self.k, self.k_cap)
        if k_next is None and cause is not None and self._can_refine():
            k_next = self._refined_k()
        refine = k_next is not None and k_next > k_used
        self.history.append(PRDPRecord(step=len(self.history), k=k_used, metric=metric, ema=ema, r=r, rc=rc,
                                       refined=refine, cause=cause if refine else None, capped_metric=capped,
                                       gap=gap, k_cap=self.k_cap, probes=probes))
        if refine:
            self._set_k(k_next)
            _log.info("PRDP: K %d -> %d (%s) at step %d, metric %.3e", k_used, self.k, cause,
                      len(self.history) - 1, metric)
        self._eval_calls = self._capped_eval_calls()
        return refine

    def finish(self, metric, *, capped: float | None = None) -> PRDPFinish:
        """The closing call, after the last epoch: the model as it will be judged, and the gap closed.

        Runs the validation at reference physics and at the caps; where the gap is open, raises K to the
        cap that closes it (as :meth:`step` does; at ``k_cap`` K_eps is measured again at this model). Warns
        (:class:`PRDPGapWarning`, naming both metrics) where the gap stays open. Nothing is added to
        :attr:`history`.

        Args:
            metric: the validation as a function (as for :meth:`step`), or its value at reference physics.
            capped: with a number, the same metric at the caps (a number cannot be searched: an open gap
                warns).
        """
        validate = metric if callable(metric) else None
        value = self._checked(self._run(validate, at_reference=self.judge == "reference")
                              if validate is not None else metric, "metric")
        self._gap_closed_at = None                  # measured once more, whatever an earlier step found
        capped = self._capped_metric(validate, capped)
        if capped is None:
            return PRDPFinish(metric=value, capped_metric=None, gap=None, k=self.k, k_cap=self.k_cap, closed=True)
        gap, probes = relative_gap(capped, value), ()
        if gap > self.gap and validate is not None:
            k_next, probes, _ = self._closing(validate, value)
            if k_next is not None and k_next > self.k:
                self._set_k(k_next)
                capped = dict(probes).get(k_next) or self._capped_at(validate, k_next)
                gap = relative_gap(capped, value)
        closed = gap <= self.gap
        if not closed:
            warnings.warn(open_gap_message(self.k, capped, value, self.gap, self.k_cap), PRDPGapWarning, stacklevel=2)
        _log.info("PRDP: finished at K %d, metric %.3e (capped %.3e, gap %.3g)", self.k, value, capped, gap)
        return PRDPFinish(metric=value, capped_metric=capped, gap=gap, k=self.k, k_cap=self.k_cap, closed=closed,
                          probes=probes)

    def _capped_metric(self, validate: Callable | None, capped) -> float | None:
        """The metric at the caps where the gap is known: given, or measured by running ``validate`` capped
        (not where K sits at ``k_cap`` with the gap found closed there)."""
        if self.judge != "reference" or self.gap is None:
            return None
        if capped is not None:
            return self._checked(capped, "capped")
        if validate is None or not self._can_refine() and self._gap_closed_at == (self.k, self.k_cap):
            return None
        return self._checked(self._run(validate, at_reference=False), "capped")

    def _capped_at(self, validate: Callable, k: int) -> float:
        """The capped metric with the target's caps at ``k`` (put back to K afterwards)."""
        try:
            self._target.set_k(k)
            return self._checked(self._run(validate, at_reference=False), "capped")
        finally:
            self._target.set_k(self.k)

    def _closing(self, validate: Callable | None, metric: float) -> tuple[int | None, tuple, str | None]:
        """Where the gap is open: the cap that closes it, the search's probes and the cause (``"gap"``, or
        ``"k_eps"`` where ``k_cap`` was raised first); ``(None, (), None)`` where K cannot move."""
        cause = "gap"
        if not self._can_refine():
            if not (self.remeasure and validate is not None and self._raise_k_cap(validate)):
                return None, (), None
            cause = "k_eps"
        if validate is None:
            return grown_cap(self.k, self.dk, self.k_cap), (), cause
        bound = self.k_cap if self.k_cap is not None else max(self.k + self.dk, self._measured_k_eps(validate))
        search = closing_cap(lambda k: self._capped_at(validate, k), metric, self.k, bound, self.gap, self.dk)
        if not search.closed and cause == "gap" and self.k_cap is not None and self.remeasure \
                and self._raise_k_cap(validate):            # open at k_cap: K_eps at this model lies above it
            more = closing_cap(lambda k: self._capped_at(validate, k), metric, search.k, self.k_cap, self.gap,
                               self.dk)
            search, cause = GapSearch(more.k, more.closed, search.probes + more.probes), "k_eps"
        return search.k, search.probes, cause

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
        # Over a torch group the ranks' metrics are compared at the next training call.
        return checked_metric(metric, what, lambda value: refuse_different_metrics(self.ranks, value))

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

    def _measured_k_eps(self, validate: Callable) -> int:
        return remeasured_k_eps(self._target, validate, self.k_eps_rtol, len(self.history))

    def _raise_k_cap(self, validate: Callable) -> bool:
        """Measure K_eps on the validation at the current model; raise ``k_cap`` if it lies above."""
        measured = self._measured_k_eps(validate)
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

    def _refined_k(self) -> int:
        return refined_cap(self.k, self.settings, self.k_cap)

    def _set_k(self, k: int) -> None:
        self.k = k
        self._target.set_k(k)

    def refine_for_health(self, ratio: float) -> bool:
        """Refine K now, for a training call whose capped solves ended with residual ratio ``ratio``
        (a layer's :class:`~fempdl.solve.health.HealthCheck` calls it); False when K is at ``k_cap``."""
        if not self._can_refine():
            return False
        k_used = self.k
        self._set_k(self._refined_k())
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
        check = HealthCheck(self.health, lambda ratio: (refine() or _cannot_refine)(ratio),
                            adjoint_limit=self.adjoint_health)
        for layer in layers:
            layer.health = check

    @property
    def ranks(self) -> Ranks | None:
        """The ranks whose metrics must agree (looked up at each step: a torch.distributed group may
        be initialised after the controller was built)."""
        return training_ranks(self._given_comm, self.comm)

    def state_dict(self) -> dict:
        """Everything needed to continue: K, the checkpoint, the history and the settings."""
        return {
            "k": self.k, "k_cap": self.k_cap, "checkpoint": self.checkpoint,
            "history": [dataclasses.asdict(rec) for rec in self.history],
            "health_refinements": [dict(event) for event in self.health_refinements],
            "health_schedules": [layer.health_schedule for layer in self._target.layers],
            "settings": dataclasses.asdict(self.settings),
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore from :meth:`state_dict` (and set the target's cap to the saved K)."""
        check_saved_settings(state["settings"], self.settings)
        self.k, self._k_cap = saved_caps(state, self.settings)
        self.checkpoint = state["checkpoint"]
        self.history = [PRDPRecord(**{**rec, "probes": tuple(tuple(p) for p in rec.get("probes", ()))})
                        for rec in state["history"]]
        self.health_refinements = [dict(event) for event in state.get("health_refinements", [])]
        schedules = state.get("health_schedules", [])        # none in a state saved before they were
        if len(schedules) == len(self._target.layers):
            for layer, schedule in zip(self._target.layers, schedules):
                layer.health_schedule = schedule
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
