"""One rule for numeric arguments (fempdl/core/checks.py): a numpy integer counts as an int and a numpy
integer or floating as a real number, bools (python or numpy) as neither; a checked value is stored as
the python number it holds, so reprs, comparisons and saved states are those of python numbers."""
import dataclasses

import numpy as np
import pytest
import torch

from fempdl import Rollout, SolveLayer, forms, mesh
from fempdl.app.runs.settings import RunSettings
from fempdl.core.checks import check_int, is_int, is_real
from fempdl.prdp import PRDP
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.options import KSPOptions

BOOLS = (True, False, np.True_, np.False_)


def test_the_predicates():
    for value in (3, np.int8(3), np.int64(3), np.uint32(3)):
        assert is_int(value) and is_real(value), value
    for value in (0.5, np.float16(0.5), np.float32(0.5), np.float64(0.5)):
        assert is_real(value) and not is_int(value), value
    for value in (*BOOLS, "3", None, 1j, np.complex128(1), np.array([3]), torch.tensor(3)):
        assert not is_int(value) and not is_real(value), value
    check_int("k", np.int64(3), minimum=1)
    for value in BOOLS:
        with pytest.raises(TypeError, match="k must be an int, got"):
            check_int("k", value, minimum=0)


@pytest.fixture(scope="module")
def heat():
    return SolveLayer(forms.heat.problem(mesh.load("lshape", h=0.3), controls=("u0",)), "lu")


def test_rollout_schedules_take_numpy_counts(heat):
    rollout = Rollout(heat, schedule=("revolve", np.int64(3)))
    assert rollout.schedule == ("revolve", 3) and type(rollout.schedule[1]) is int
    assert "schedule=('revolve', 3)" in repr(rollout)
    staged = Rollout(heat, schedule=("multistage", np.int32(2), np.int64(0)))
    assert staged.schedule == ("multistage", 2, 0) and all(type(s) is int for s in staged.schedule[1:])
    u0 = torch.rand(heat.problem.control_size("u0"), dtype=torch.float64, requires_grad=True)
    rollout(u0, np.int64(4)).sum().backward()
    assert rollout.schedule_stats.adjoint_steps == 4 and torch.isfinite(u0.grad).all()
    for value in BOOLS:
        with pytest.raises(ValueError, match="revolve snapshots must be an int >= 1, got"):
            Rollout(heat, schedule=("revolve", value))
        with pytest.raises(ValueError, match="multistage snapshots in memory must be an int >= 0, got"):
            Rollout(heat, schedule=("multistage", value, 1))


def test_run_settings_take_numpy_numbers():
    settings = RunSettings(epochs=np.int64(3), seed=np.uint16(7), stop_after=np.int32(2),
                           stop_at_time=np.float32(1.5), checkpoint_every=np.float64(0.25))
    assert (settings.epochs, settings.seed, settings.stop_after, settings.stop_at_time,
            settings.checkpoint_every) == (3, 7, 2, 1.5, 0.25)
    for name, kind in (("epochs", int), ("seed", int), ("stop_after", int), ("stop_at_time", float),
                       ("checkpoint_every", float)):
        assert type(getattr(settings, name)) is kind, name
    assert RunSettings(epochs=3) == dataclasses.replace(settings, seed=None, stop_after=None, stop_at_time=None,
                                                        checkpoint_every=RunSettings().checkpoint_every)
    for value in BOOLS:
        with pytest.raises(ValueError, match="epochs must be a positive int or None, got"):
            RunSettings(epochs=value)
        with pytest.raises(ValueError, match="checkpoint_every must be a finite number of seconds >= 0, got"):
            RunSettings(checkpoint_every=value)       # True was taken as one second


def test_prdp_takes_numpy_numbers(heat):
    layer = SolveLayer(heat.problem, KSPOptions.preset("jacobi", max_it=5))
    ctrl = PRDP(layer, k0=np.int64(2), tau_step=np.float32(0.95), k_cap=np.int32(40), growth=np.float64(2))
    assert ctrl.k == 2 and type(ctrl.settings.k0) is int and type(ctrl.settings.k_cap) is int
    assert type(ctrl.settings.tau_step) is float and ctrl.settings.tau_step == float(np.float32(0.95))
    assert type(ctrl.settings.growth) is float
    assert layer.options.max_it == 2 and type(layer.options.max_it) is int
    with pytest.raises(TypeError, match="k0 must be an int, got"):
        PRDP(k0=np.True_)
    for value in BOOLS:
        with pytest.raises(ValueError, match=r"tau_step must be a number in \(0, 1\], got"):
            PRDP(tau_step=value)


def test_solver_options_take_numpy_numbers():
    options = KSPOptions.preset("cg", max_it=np.int64(5), rtol=np.float32(0.5), atol=np.float64(1e-12))
    assert (options.max_it, options.rtol, options.atol) == (5, float(np.float32(0.5)), 1e-12)
    assert type(options.max_it) is int and type(options.rtol) is float and type(options.atol) is float
    assert options == KSPOptions.preset("cg", max_it=5, rtol=0.5, atol=1e-12)
    assert hash(options) == hash(KSPOptions.preset("cg", max_it=5, rtol=0.5, atol=1e-12))
    newton = NewtonOptions(max_it=np.int64(4), rtol=np.float32(0.25), damping=np.float32(0.5))
    assert (newton.max_it, newton.rtol, newton.damping) == (4, 0.25, 0.5)
    assert type(newton.max_it) is int and type(newton.rtol) is float and type(newton.damping) is float
    for value in BOOLS:
        with pytest.raises(TypeError, match="rtol must be a float or None, got"):
            KSPOptions.preset("cg", rtol=value)
        with pytest.raises(ValueError, match=r"NewtonOptions.damping must be in \(0, 1\], got"):
            NewtonOptions(damping=value)


def test_forms_take_numpy_numbers():
    msh = mesh.load("lshape", h=0.3)
    problem = forms.heat.problem(msh, controls=("u0",), dt=np.float32(0.01), theta=np.float32(0.5),
                                 degree=np.int64(1))
    assert float(problem.constants["dt"].value) == pytest.approx(0.01)
    for value in BOOLS:
        with pytest.raises(ValueError, match="theta must be in"):
            forms.heat.problem(msh, theta=value)
        with pytest.raises(ValueError, match="degree must be an int >= 1, got"):
            forms.heat.problem(msh, degree=value)
