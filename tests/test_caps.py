"""The cap as one value and what PRDP moves through one protocol.

``Caps`` validates and compares as a value; ``layer.caps`` reads and sets both layer kinds' caps (a
refused value leaves every cap as it was); ``as_target`` makes one interface of every kind of PRDP
target, and the methods (PRDP, K_eps, k0, preflight) reach the layers' caps only through it.
"""
from __future__ import annotations

import dataclasses

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import torch

from fempdl import (
    PRDP,
    Caps,
    KSPOptions,
    NewtonCaps,
    NewtonOptions,
    NonlinearSolveLayer,
    Rollout,
    SolveLayer,
    forms,
    k_eps,
)
from fempdl.layer.cap_target import CapFunction, CapTargets, LayerCaps, MaxItAttribute, as_target

F64 = torch.float64


@pytest.fixture(scope="module")
def square():
    return dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)


@pytest.fixture(scope="module")
def heat(square):
    return forms.heat.problem(square, controls=("u0",), dt=0.05)


@pytest.fixture(scope="module")
def diffusion(square):
    return forms.nonlinear_diffusion.problem(square, controls=("f",))


@pytest.mark.parametrize("fields,error,message", [
    ({"max_it": 0}, ValueError, r"Caps.max_it must be >= 1, got 0"),
    ({"max_it": 2.5}, TypeError, r"Caps.max_it must be an int"),
    ({"max_it": True}, TypeError, r"Caps.max_it must be an int, got True"),
    ({"max_it": 3, "inner_max_it": -1}, ValueError, r"Caps.inner_max_it must be >= 1"),
])
def test_caps_refuse_what_no_solve_can_run_at(fields, error, message):
    with pytest.raises(error, match=message):
        Caps(**fields)


def test_caps_are_a_frozen_value():
    caps = Caps(np.int64(4), inner_max_it=20)
    assert type(caps.max_it) is int and caps == Caps(4, 20) and hash(caps) == hash(Caps(4, 20))
    assert repr(Caps(5)) == "Caps(max_it=5)" and repr(caps) == "Caps(max_it=4, inner_max_it=20)"
    assert Caps() == Caps(None, None)
    with pytest.raises(dataclasses.FrozenInstanceError):
        caps.max_it = 5


def test_a_linear_layer_reads_and_sets_its_cap_as_caps(heat):
    layer = SolveLayer(heat, KSPOptions.preset("jacobi", max_it=7))
    assert layer.caps == Caps(7) == as_target(layer).layers[0].caps
    layer.caps = Caps(3)
    assert layer.max_it == 3 and layer.system.max_it == 3
    with pytest.raises(ValueError, match=r"a linear solve has one cap, max_it; got Caps\(max_it=3, inner_max_it=2\)"):
        layer.caps = Caps(3, inner_max_it=2)
    with pytest.raises(TypeError, match="caps must be a fempdl.Caps, got int; or set max_it"):
        layer.caps = 3
    assert layer.caps == Caps(3)
    layer.load_state_dict({"_extra_state": {"max_it": 9}})     # a record saved before the inner cap was in it
    assert layer.caps == Caps(9) and layer.state_dict()["_extra_state"] == {"max_it": 9, "inner_max_it": None}
    layer.close()


def test_a_newton_layer_checks_both_caps_before_either_moves(diffusion):
    layer = NonlinearSolveLayer(diffusion, NewtonOptions(max_it=2, ksp="lu"), diff="unrolled")
    with pytest.raises(ValueError, match="no effect with ksp_type='preonly'"):
        layer.caps = Caps(5, inner_max_it=3)
    assert layer.caps == Caps(2)
    cg = NonlinearSolveLayer(diffusion, NewtonOptions(max_it=2, ksp=KSPOptions.preset("cg", max_it=4)))
    cg.caps = Caps(3, inner_max_it=6)
    assert (cg.max_it, cg.inner_max_it) == (3, 6) and cg.options.ksp.max_it == 6
    assert cg.state_dict()["_extra_state"] == {"max_it": 3, "inner_max_it": 6}
    layer.close()
    cg.close()


def test_as_target_makes_one_interface_of_every_kind(heat, diffusion):
    linear = SolveLayer(heat, KSPOptions.preset("jacobi", max_it=7))
    newton = NonlinearSolveLayer(diffusion, NewtonOptions(max_it=2, ksp=KSPOptions.preset("cg", max_it=4)))
    rollout = Rollout(linear, state="u0")
    seen = []

    class Inverse:            # e.g. a SIP inverse: its cap is its max_it
        max_it = 2

    inverse = Inverse()
    assert as_target(linear) == LayerCaps((linear,), call=linear) and not as_target(linear).counts_newton_steps
    assert as_target(newton).counts_newton_steps and as_target(rollout).call is rollout
    assert as_target(rollout).layers == (linear,)
    assert isinstance(as_target(inverse), MaxItAttribute) and as_target(inverse).k == 2
    assert isinstance(as_target(seen.append), CapFunction) and as_target(None).layers == ()
    both = as_target([linear, newton, inverse])
    assert isinstance(both, CapTargets) and both.layers == (linear, newton) and both.call is None
    rule = NewtonCaps(newton, "both", inner_per_k=3)
    assert as_target(rule) is rule and as_target(as_target(linear)) == as_target(linear)
    with both.kept(), rule.kept():
        both.set_k(5)
        assert (linear.caps, newton.caps, inverse.max_it, both.k) == (Caps(5), Caps(5, 4), 5, 5)
        rule.set_k(2)
        assert newton.caps == Caps(2, 6) and rule.k == 2
    assert (linear.caps, newton.caps, inverse.max_it, rule.k) == (Caps(7), Caps(2, 4), 2, None)
    as_target(seen.append).set_k(4)
    assert seen == [4]
    with pytest.raises(TypeError, match="got a str, which has no max_it attribute"):
        as_target("layer")
    for layer in (linear, newton):
        layer.close()


def test_k_eps_of_counts_follows_the_target(diffusion):
    """A NewtonCaps rule records the converged caps and answers by its rule; plain layers take the most Newton
    steps of their Newton layers and the most iterations of their linear ones (at least 1)."""
    newton = NonlinearSolveLayer(diffusion, NewtonOptions(max_it=2, ksp=KSPOptions.preset("cg", max_it=4)))
    rule = NewtonCaps(newton, "both", inner_per_k=5)
    assert rule.k_eps_from([(3, 40)]) == 8 and rule.converged.newton_steps == 3     # max(3, ceil(40 / 5))
    rule.set_k(10)
    assert newton.caps == Caps(3, 40)               # "both" is bounded by the converged caps once known
    newton.close()
    assert CapTargets(()).k_eps_from([(3, 40), (None, 25)]) == 25
    assert CapTargets(()).k_eps_from([(3, 40)]) == 3
    assert CapTargets(()).k_eps_from([(None, 0)]) == 1


def test_prdp_moves_a_rollout_through_its_target_and_records_what_ranks_compare(heat):
    layer = SolveLayer(heat, KSPOptions.preset("jacobi", max_it=7))
    rollout = Rollout(layer, state="u0")
    ctrl = PRDP(rollout, k0=2, k_cap=6, delta=2, ema_window=1)
    assert layer.caps == Caps(2) and ctrl.layers == [layer]
    assert layer._prdp_record() == (0, None, 6) == ctrl.steps_record
    for metric in (1.0, 0.5, 0.499):      # progress since the start, then a plateau: K 2 -> 3
        ctrl.step(metric)
    assert layer.caps == Caps(3) and layer._prdp_record() == (3, 0.499, 6)
    u0 = torch.linspace(0.0, 1.0, heat.output_size, dtype=F64)
    assert k_eps(rollout, initial=u0, steps=2, rtol=1e-6) > 3 and layer.caps == Caps(3)   # measured, put back
    del ctrl
    assert layer._prdp_record() == (0, None, None)        # held weakly: a layer does not keep PRDP alive
    layer.close()
