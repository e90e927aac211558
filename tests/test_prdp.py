"""The PRDP controller on synthetic metric sequences."""
from __future__ import annotations

import math

import pytest

from fempdl.methods.prdp import PRDP


class Target:
    max_it = None


def run(metrics, **kw):
    ctrl = PRDP(**kw)
    decisions = [ctrl.step(m) for m in metrics]
    return ctrl, decisions


def test_ema_and_ratios_follow_the_algorithm():
    ctrl, _ = run([1.0, 0.5, 0.4, 0.39], ema_window=3, delta=3)
    alpha = 0.5
    ema = [1.0]
    for m in (0.5, 0.4, 0.39):
        ema.append(alpha * m + (1 - alpha) * ema[-1])
    assert ctrl.ema == pytest.approx(ema, rel=1e-15)
    assert [rec.r for rec in ctrl.history[:3]] == [None] * 3        # at most delta entries: no decision
    assert ctrl.history[3].r == pytest.approx(ema[3] / ema[1])      # ema[-1] / ema[-delta]


def test_steady_improvement_holds_and_plateau_refines():
    improving = [0.5 ** i for i in range(10)]                      # r = 0.25 < tau_step
    ctrl, decisions = run(improving, ema_window=1)
    assert not any(decisions) and ctrl.k == 1
    plateau = improving + [improving[-1]] * 3
    ctrl, decisions = run(plateau, ema_window=1)
    assert decisions.count(True) == 1 and ctrl.k == 2
    refine_at = decisions.index(True)
    rec = ctrl.history[refine_at]
    assert rec.r > 0.95 and rec.rc < 0.9 and ctrl.checkpoint == rec.ema


def test_stagnation_across_a_refinement_stops_refining():
    """After a refinement that no longer improves the plateau (rc in [tau_stop, 1]), K holds."""
    target = Target()
    metrics = [1.0, 0.5, 0.25, 0.2, 0.2, 0.2] + [0.199] * 12
    ctrl, decisions = run(metrics, target=target, ema_window=1, delta=3, k0=4, dk=2)
    assert decisions.count(True) == 1 and ctrl.k == 6 and target.max_it == 6
    later = [rec for rec in ctrl.history[decisions.index(True) + 1:] if rec.rc is not None]
    assert later and all(0.9 <= rec.rc <= 1.0 and not rec.refined for rec in later)


def test_refinement_resumes_after_further_improvement():
    metrics = [1.0, 0.5, 0.25, 0.25, 0.25, 0.24, 0.24] + [0.1] * 5
    ctrl, decisions = run(metrics, ema_window=1)
    assert decisions.count(True) == 2 and ctrl.k == 3


def test_a_worsening_metric_refines():
    # The initially divergent regime: the metric grows from the start (rc > 1).
    ctrl, decisions = run([1.0, 1.2, 1.5, 1.6, 1.65], ema_window=1)
    assert decisions[3] and ctrl.history[3].rc > 1.0


def test_first_plateau_within_tau_stop_of_the_start_holds():
    """c starts at the first metric: a run that plateaus at once within 10% holds K."""
    ctrl, decisions = run([1.0, 0.97, 0.96, 0.96, 0.96, 0.96], ema_window=1)
    assert not any(decisions) and ctrl.k == 1


def test_k_never_exceeds_k_cap():
    worsening = [1.0 * 1.1 ** i for i in range(40)]
    ctrl, decisions = run(worsening, ema_window=1, k0=2, dk=3, k_cap=10)
    assert ctrl.k == 10 and max(rec.k for rec in ctrl.history) == 10
    assert all(not d for d, rec in zip(decisions, ctrl.history) if rec.k == 10)


def test_state_dict_round_trip_continues_identically():
    metrics = [1.0, 0.6, 0.5, 0.49, 0.49, 0.48, 0.3, 0.29, 0.29, 0.29, 0.29]
    full = PRDP(ema_window=4)
    expected = [full.step(m) for m in metrics]
    first = PRDP(ema_window=4)
    got = [first.step(m) for m in metrics[:5]]
    target = Target()
    resumed = PRDP(target=target, ema_window=4)
    resumed.load_state_dict(first.state_dict())
    assert target.max_it == first.k
    got += [resumed.step(m) for m in metrics[5:]]
    assert got == expected and resumed.state_dict() == full.state_dict()
    with pytest.raises(ValueError, match="saved PRDP settings differ"):
        PRDP(ema_window=5).load_state_dict(first.state_dict())


def test_drives_several_targets_and_callbacks():
    a, b, seen = Target(), Target(), []
    PRDP([a, b], k0=3)
    assert a.max_it == b.max_it == 3
    ctrl = PRDP(seen.append, k0=2)
    ctrl.step(1.0)
    assert seen == [2]


@pytest.mark.parametrize("kwargs,error,match", [
    (dict(k0=0), ValueError, "k0 must be >= 1"),
    (dict(dk=1.5), TypeError, "dk must be an int"),
    (dict(tau_step=1.5), ValueError, r"tau_step must be a number in \(0, 1\]"),
    (dict(tau_stop=0), ValueError, "tau_stop"),
    (dict(delta=1), ValueError, "delta must be >= 2"),
    (dict(k0=5, k_cap=3), ValueError, "k_cap must be >= 5"),
    (dict(target=object()), TypeError, "has no max_it attribute"),
])
def test_bad_settings(kwargs, error, match):
    with pytest.raises(error, match=match):
        PRDP(**kwargs)


@pytest.mark.parametrize("metric", [math.nan, math.inf, 0.0, -1.0])
def test_bad_metric(metric):
    with pytest.raises(ValueError, match="metric must be finite and > 0"):
        PRDP().step(metric)


def test_guard_refines_at_once_on_a_rise_above_the_best():
    """A metric that jumps above guard x its best (and its previous value) refines before the
    grace interval is over; the plain algorithm waits for delta entries and the EMA."""
    metrics = [1.0, 0.5, 2.0, 3.0]
    plain, plain_decisions = run(metrics, ema_window=4, delta=3)
    guarded, decisions = run(metrics, ema_window=4, delta=3, guard=1.5)
    assert plain_decisions == [False, False, False, True]
    assert decisions == [False, False, True, True] and guarded.k == 3
    assert [rec.cause for rec in guarded.history] == [None, None, "rise", "rise"]
    # A small rise (below guard x best) or a fall does not trigger it.
    _, decisions = run([1.0, 0.5, 0.6, 0.55], ema_window=4, delta=3, guard=1.5)
    assert not any(decisions)


def test_growth_multiplies_the_cap_and_respects_k_cap():
    plateau = [1.0, 0.5, 0.25] + [0.25] * 2 + [0.1] * 3 + [0.1] * 2
    ctrl, decisions = run(plateau, ema_window=1, k0=4, dk=1, growth=2.0, k_cap=10)
    ks = [rec.k for rec in ctrl.history]
    assert decisions.count(True) == 2 and sorted(set(ks)) == [4, 8, 10] and ctrl.k == 10


@pytest.mark.parametrize("kw", [{"guard": 1.0}, {"guard": float("nan")}, {"guard": True},
                                {"growth": 0.5}, {"growth": float("inf")}])
def test_guard_and_growth_are_validated(kw):
    with pytest.raises(ValueError, match=next(iter(kw))):
        PRDP(**kw)


def test_state_without_guard_and_growth_loads_as_plain_algorithm():
    ctrl, _ = run([1.0, 0.5, 0.5, 0.5], ema_window=1)
    state = ctrl.state_dict()
    for key in ("guard", "growth"):
        del state["settings"][key]
    for rec in state["history"]:
        del rec["cause"]
    fresh = PRDP(ema_window=1, growth=1.0)         # what a state saved before growth existed ran
    fresh.load_state_dict(state)
    assert fresh.k == ctrl.k and [r.refined for r in fresh.history] == [r.refined for r in ctrl.history]
    with pytest.raises(ValueError, match="guard"):
        PRDP(ema_window=1, growth=1.0, guard=2.0).load_state_dict(state)
    with pytest.raises(ValueError, match=r"'growth': \(1.0, 1.5\)"):
        PRDP(ema_window=1).load_state_dict(state)    # the default now grows by half


def test_refinements_are_logged(caplog):
    improving = [0.5 ** i for i in range(10)]
    with caplog.at_level("INFO", logger="fempdl.methods.prdp"):
        ctrl, decisions = run(improving + [improving[-1]] * 3, ema_window=1, k0=3, dk=2)
    step = decisions.index(True)
    assert [(r.name, r.levelname, r.getMessage()) for r in caplog.records] == [
        ("fempdl.methods.prdp", "INFO", f"PRDP: K 3 -> 5 (plateau) at step {step}, metric {improving[-1]:.3e}")]


def test_ranks_print_as_their_group_and_size():
    from mpi4py import MPI

    from fempdl.core.ranks import Ranks

    assert repr(Ranks(MPI.COMM_WORLD, torch_group=False)) == "Ranks(MPI communicator 'MPI_COMM_WORLD', size 1)"
