"""The settings of a PRDP controller and the record of one of its steps.

:class:`PRDPSettings` is validated once and is also the ``[prdp]`` section of
a scene file; :class:`PRDPRecord` is one entry of ``PRDP.history``. The
rule they parametrise is :mod:`fempdl.methods.prdp`'s.
"""
from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable

from fempdl.core.checks import check_int, is_real

__all__ = ["PRDPFinish", "PRDPRecord", "PRDPSettings", "check_saved_settings", "refined_cap", "JUDGES", "SETTING_NAMES"]

#: The physics a metric given as a function is computed with (``PRDPSettings.judge``).
JUDGES = ("reference", "capped")


@dataclasses.dataclass(frozen=True)
class PRDPRecord:
    """One call of :meth:`PRDP.step`: the K in force while ``metric`` was
    measured, the smoothed metric, the ratios (None before a decision is
    possible or when not computed), whether K was raised afterwards and why,
    and, where the gap is known (every step of a validation given as a
    function), the capped metric, the gap and the probes of a search that
    closed it."""

    step: int
    k: int
    metric: float
    ema: float
    r: float | None
    rc: float | None
    refined: bool
    cause: str | None = None      # when refined: "plateau", "rise" (the guard), "gap" or "k_eps" (module docstring)
    capped_metric: float | None = None     # the metric at the caps at k, where the gap is known
    gap: float | None = None               # |capped - reference| / min(capped, reference), where known
    k_cap: int | None = None               # the cap's upper bound after this step (raised by "k_eps")
    probes: tuple = ()                     # (K, capped metric) of the search that closed an open gap


@dataclasses.dataclass(frozen=True)
class PRDPFinish:
    """What :meth:`PRDP.finish` found: the validation metric at reference physics (the model as judged),
    at the caps, their gap, the cap K and ``k_cap`` after closing it, whether it is closed (within
    ``gap``; True where no gap is known: ``judge="capped"``, ``gap=None``, or a number without its capped
    value), and the probes of the search that closed it."""

    metric: float
    capped_metric: float | None
    gap: float | None
    k: int
    k_cap: int | None
    closed: bool
    probes: tuple = ()


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
    growth: float = _setting(1.5, "a refinement of the plateau rule sets K to max(K + dk, ceil(growth K)) (1: the "
                                  "paper's K + dk)", float, minimum=1.0)
    judge: str = _setting("reference", "the physics a metric given as a function is computed with: reference "
                                       "(converged, the model as deployed) or capped (a model deployed with the "
                                       "capped solver)", str, choices=JUDGES)
    gap: float | None = _setting(0.05, "at every step of a validation given as a function, raise K to the cap "
                                       "at which the capped and the reference metric differ by at most this "
                                       "fraction (none: never)", float, minimum=_POSITIVE)
    remeasure: bool = _setting(True, "where the gap stays open at k_cap, measure K_eps again at the current "
                                     "model and raise k_cap to it", bool)
    k_eps_rtol: float = _setting(1e-8, "the tolerance of converged solves when K_eps is measured again", float,
                                 minimum=_POSITIVE, maximum=1.0)
    health: float | None = _setting(1.0, "refine at once when a training call's capped solve ends with its residual "
                                         "above health x its start, and solve it again (none: never)", float,
                                    minimum=_POSITIVE)
    adjoint_health: float | None = _setting(0.01, "where a layer's gradient is the implicit approximation (capped "
                                                 "Krylov, matrix controls), refine at once when a training "
                                                 "call's capped adjoint ends above this fraction of its start "
                                                 "residual (none: the health limit)", float, minimum=_POSITIVE)

    def __post_init__(self):
        check_int("k0", self.k0, minimum=1)
        check_int("dk", self.dk, minimum=1)
        check_int("delta", self.delta, minimum=2)
        check_int("ema_window", self.ema_window, minimum=1)
        if self.k_cap is not None:
            check_int("k_cap", self.k_cap, minimum=self.k0)
        # Python numbers, not numpy ones: the settings are saved in a PRDP state (a weights_only checkpoint)
        # and compared with a saved state's.
        for name in ("k0", "dk", "delta", "ema_window", "k_cap"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, int(getattr(self, name)))
        for name in ("tau_step", "tau_stop"):
            value = getattr(self, name)
            if not is_real(value) or not 0.0 < value <= 1.0:
                raise ValueError(f"{name} must be a number in (0, 1], got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.guard is not None:
            if not (is_real(self.guard) and 1.0 < self.guard < math.inf):
                raise ValueError(f"guard must be a finite number > 1 (or None: off), got {self.guard!r}")
            object.__setattr__(self, "guard", float(self.guard))
        if not (is_real(self.growth) and 1.0 <= self.growth < math.inf):
            raise ValueError(f"growth must be a finite number >= 1, got {self.growth!r}")
        object.__setattr__(self, "growth", float(self.growth))
        if self.judge not in JUDGES:
            raise ValueError(f"judge must be one of {list(JUDGES)}, got {self.judge!r}")
        if self.gap is not None:
            if not (is_real(self.gap) and 0.0 < self.gap < math.inf):
                raise ValueError(f"gap must be a finite relative difference > 0 (or None: off), got {self.gap!r}")
            object.__setattr__(self, "gap", float(self.gap))
        if not isinstance(self.remeasure, bool):
            raise TypeError(f"remeasure must be True or False, got {self.remeasure!r}")
        if not (is_real(self.k_eps_rtol) and 0.0 < self.k_eps_rtol < 1.0):
            raise ValueError(f"k_eps_rtol must be a number in (0, 1), got {self.k_eps_rtol!r}")
        object.__setattr__(self, "k_eps_rtol", float(self.k_eps_rtol))
        for name in ("health", "adjoint_health"):
            value = getattr(self, name)
            if value is not None:
                if not (is_real(value) and 0.0 < value < math.inf):
                    raise ValueError(f"{name} must be a finite residual ratio > 0 (or None: off), got {value!r}")
                object.__setattr__(self, name, float(value))


SETTING_NAMES = frozenset(f.name for f in dataclasses.fields(PRDPSettings))


def refined_cap(k: int, settings: PRDPSettings, k_cap: int | None) -> int:
    """The cap after a refinement of the rule (or of the health check): max(K + dk, ceil(growth K)), at most
    ``k_cap``."""
    k = max(k + settings.dk, math.ceil(settings.growth * k - 1e-9))
    return k if k_cap is None else min(k, k_cap)


def check_saved_settings(saved: dict, settings: PRDPSettings) -> None:
    """Refuse a saved controller's settings that differ from ``settings``, naming them.

    States saved before guard and growth existed ran plain Algorithm 4 (growth 1); health acts between
    validations and leaves the saved history valid, so a state saved before it resumes with either. The
    judge, gap, remeasure and adjoint_health settings act at the steps to come: a state saved before them
    resumes too.
    """
    mine = dataclasses.asdict(settings)
    later = {key: mine[key] for key in ("judge", "gap", "remeasure", "k_eps_rtol", "adjoint_health")}
    merged = {"guard": None, "growth": 1.0, "health": settings.health, **later, **saved}
    if merged != mine:
        changed = {k: (merged.get(k), v) for k, v in mine.items() if merged.get(k) != v}
        raise ValueError(f"saved PRDP settings differ from this controller's (saved, current): {changed}")


def checked_metric(metric, what: str, agree: Callable[[float], None]) -> float:
    """``metric`` as a float: one number (a Python or numpy number, a one-element tensor or array), finite
    and > 0; a TypeError or ValueError naming ``what`` otherwise. ``agree(value)`` runs between the
    conversion and the range check, on every rank alike (a collective: a NaN on one rank must not skip it)."""
    if isinstance(metric, bool) or not isinstance(metric, (int, float)) and not hasattr(metric, "__float__"):
        raise TypeError(f"{what} must be a number (or a function returning one), got {type(metric).__name__}")
    size = getattr(metric, "numel", getattr(metric, "size", lambda: 1))
    size = size() if callable(size) else size
    if size != 1:
        raise ValueError(f"{what} must be one number, got a {type(metric).__name__} of shape "
                         f"{tuple(metric.shape)}: reduce it to one (e.g. .mean())")
    metric = float(metric)
    agree(metric)
    if not math.isfinite(metric) or metric <= 0.0:
        raise ValueError(f"{what} must be finite and > 0 (a validation error), got {metric!r}")
    return metric


def saved_caps(state: dict, settings: PRDPSettings) -> tuple[int, int | None]:
    """(K, k_cap) of a saved controller's state, checked: K an int >= 1 and within the saved k_cap (a
    state edited by hand, or another controller's, is refused rather than set on the layer); a state saved
    before k_cap was has the settings' k_cap, which a re-measured K_eps may have passed."""
    k_cap = state.get("k_cap", settings.k_cap)
    if k_cap is not None:
        check_int("a saved PRDP state's k_cap", k_cap, minimum=1)
    k = state["k"]
    check_int("a saved PRDP state's k", k, minimum=1, hint="the state was not saved by PRDP.state_dict()")
    if "k_cap" in state and k_cap is not None and k > k_cap:     # before k_cap was saved, a re-measure passed it
        raise ValueError(f"a saved PRDP state's k ({k}) is above its k_cap ({k_cap}): the state was not saved by "
                         "PRDP.state_dict()")
    return int(k), (None if k_cap is None else int(k_cap))