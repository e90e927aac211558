"""A Rollout refuses what its step layer refuses, with or without a checkpoint schedule (the scheduled path
calls the system directly, and once skipped the layer's checks): inputs of the wrong type, size, dtype or
sign, non-finite controls, a time step <= 0 in any step; a second backward under a schedule gives the
gradient again; a multistage state that cannot be written is named where it happens."""
import os
import subprocess
import sys

from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, SolveLayer, forms, mesh

SCHEDULES = [None, ("revolve", 2)]


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.25)


@pytest.fixture(scope="module")
def heat(lshape):
    step = SolveLayer(forms.heat.problem(lshape, controls=("u0", "f")), "lu")
    yield step
    step.close()


@pytest.fixture(scope="module")
def newton(lshape):
    problem = forms.nonlinear_diffusion.problem(lshape, controls=("u0", "kappa"), alpha=2.0, dt=0.01)
    step = NonlinearSolveLayer(problem, NewtonOptions(rtol=1e-12, ksp="lu"))
    yield step
    step.close()


@pytest.mark.parametrize("schedule", SCHEDULES)
def test_a_negative_kappa_is_refused_as_the_step_refuses_it(newton, schedule):
    n = newton.problem.output_size
    kappa = -torch.ones(newton.problem.control_size("kappa"), dtype=torch.float64)
    with pytest.raises(ValueError, match=r"control 'kappa' must be > 0 everywhere .* the lowest -1"):
        Rollout(newton, "u0", schedule=schedule)(torch.zeros(n, dtype=torch.float64), 3, kappa=kappa)


@pytest.mark.parametrize("schedule", SCHEDULES)
def test_a_nonfinite_control_is_named_not_a_singular_matrix(heat, schedule):
    f = torch.ones(heat.problem.control_size("f"), dtype=torch.float64)
    f[3] = float("nan")
    with pytest.raises(ValueError, match=r"control 'f' contains 1 NaN/inf value\(s\)"):
        Rollout(heat, "u0", schedule=schedule)(torch.zeros(heat.problem.output_size, dtype=torch.float64), 3, f=f)


@pytest.mark.parametrize("schedule", SCHEDULES)
def test_an_initial_state_of_the_wrong_kind_is_named(heat, schedule):
    rollout, n = Rollout(heat, "u0", schedule=schedule), heat.problem.output_size
    with pytest.raises(TypeError, match=r"initial has dtype torch.int64; use float32 or float64"):
        rollout(torch.ones(n, dtype=torch.int64), 3)
    with pytest.raises(TypeError, match=r"initial must be a torch.Tensor, \(B, n\) or \(n,\), got ndarray"):
        rollout(np.ones(n), 3)
    with pytest.raises(ValueError, match=rf"initial must be \(B, {n}\) or \({n},\).* got shape \({n + 1},\)"):
        rollout(torch.ones(n + 1, dtype=torch.float64), 3)
    with pytest.raises(ValueError, match=r"control 'f' has shape \(2,\)"):
        rollout(torch.ones(n, dtype=torch.float64), 3, f=torch.ones(2, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"constants\['dt'\] must be numbers, one per step, got 'fast'"):
        rollout(torch.ones(n, dtype=torch.float64), 3, constants={"dt": "fast"})
    with pytest.raises(TypeError, match=r"outputs must be a sequence of state indices into 0 ... 3, e.g. \[3\]"):
        rollout(torch.ones(n, dtype=torch.float64), 3, outputs=3)


@pytest.mark.parametrize("schedule", SCHEDULES)
@pytest.mark.parametrize("kind", ["heat", "newton"])
def test_a_time_step_at_or_below_zero_is_refused_at_every_step(heat, newton, kind, schedule):
    step = heat if kind == "heat" else newton
    rollout, n = Rollout(step, "u0", schedule=schedule), step.problem.output_size
    u0 = torch.full((n,), 0.1, dtype=torch.float64)
    with pytest.raises(ValueError, match=r"Constant 'dt' must be > 0 \(problem.positive\), got -0.05 at step 2"):
        rollout(u0, 4, constants={"dt": [0.01, 0.02, -0.05, 0.01]})
    with pytest.raises(ValueError, match=r"Constant 'dt' must be > 0 \(problem.positive\), got 0 at step 0"):
        rollout(u0, 2, constants={"dt": [0.0, 0.01]})
    assert step.problem.constants["dt"].value == pytest.approx(0.01)     # nothing was set
    step.problem.constants["dt"].value = -0.5                               # set by hand: refused at the call
    try:
        with pytest.raises(ValueError, match=r"Constant 'dt' must be > 0 \(problem.positive\), got -0.5;"):
            rollout(u0, 2)
        with pytest.raises(ValueError, match=r"Constant 'dt' must be > 0"):
            step(u0=u0)
    finally:
        step.problem.constants["dt"].value = 0.01
    assert float(rollout(u0, 2)[-1].abs().max()) < 1.0                    # a positive dt still runs


def test_a_constant_given_per_step_is_checked_per_step_not_at_its_value_now(heat):
    """dt given for every step: the value the Constant holds outside the rollout is not the one it runs."""
    u0 = torch.full((heat.problem.output_size,), 0.1, dtype=torch.float64)
    heat.problem.constants["dt"].value = 0.0
    try:
        for schedule in SCHEDULES:
            states = Rollout(heat, "u0", schedule=schedule)(u0, 3, constants={"dt": [0.01] * 3})
            assert float(states[-1].abs().max()) > 0
        heat.problem.constants["dt"].value = float("nan")
        with pytest.raises(ValueError, match=r"^Constant 'dt' is nan; give it a finite value$"):
            heat(u0=u0)
    finally:
        heat.problem.constants["dt"].value = 0.01


def test_declared_bounds_of_constants_can_be_lifted_and_are_checked(lshape):
    problem = forms.oseen.problem(lshape, controls=("u_prev",))
    assert problem.positive == {"nu", "dt"} and problem.nonnegative == {"grad_div"}
    problem.constants["grad_div"].value = -1.0
    layer = SolveLayer(problem, "lu")
    with pytest.raises(ValueError, match=r"Constant 'grad_div' must be >= 0 \(problem.nonnegative\), got -1"):
        layer(u_prev=torch.zeros(problem.control_size("u_prev"), dtype=torch.float64))
    problem.nonnegative = ()                          # on purpose: solved
    assert torch.isfinite(layer(u_prev=torch.zeros(problem.control_size("u_prev"), dtype=torch.float64))).all()
    with pytest.raises(ValueError, match=r"positive names \['tau'\], which are not among this problem's controls"):
        problem.positive = ("tau",)
    layer.close()


@pytest.mark.parametrize("schedule", ["all", ("revolve", 2), ("multistage", 1, 1)])
def test_a_second_backward_under_a_schedule_adds_the_gradient_again(newton, schedule, tmp_path):
    """retain_graph=True and a second backward: the schedule runs again from u_0 at the forward's dt (moved
    since), so a Newton rollout's adjoint, which needs its states, gets them as the forward made them."""
    n = newton.problem.output_size
    g = torch.Generator().manual_seed(0)
    u0 = (0.5 * torch.rand(n, dtype=torch.float64, generator=g)).requires_grad_()
    kappa = (1.0 + torch.rand(2, newton.problem.control_size("kappa"), dtype=torch.float64, generator=g))
    kappa.requires_grad_()
    w = torch.rand(n, dtype=torch.float64, generator=g)
    dt = newton.problem.constants["dt"]
    grads = {}
    for how in (None, schedule):
        u0.grad = kappa.grad = None
        rollout = Rollout(newton, "u0", schedule=how, disk_dir=str(tmp_path))
        loss = (w * rollout(u0, 5, kappa=kappa, outputs=[3, 5])).square().sum()
        dt.value = 0.1                     # moved after the forward: both backwards run at the forward's 0.01
        try:
            loss.backward(retain_graph=True)
            loss.backward()
        finally:
            dt.value = 0.01
        grads[how] = (u0.grad.clone(), kappa.grad.clone())
    for unscheduled, scheduled in zip(grads[None], grads[schedule]):
        torch.testing.assert_close(scheduled, unscheduled, rtol=1e-9, atol=1e-14)
    assert float(grads[None][1].abs().max()) > 0


FILE_SIZE_LIMIT = """
import resource, sys
from mpi4py import MPI
import torch
from fempdl import Rollout, SolveLayer, forms, mesh
step = SolveLayer(forms.heat.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.1), controls=("u0", "kappa")), "lu")
rollout = Rollout(step, "u0", schedule=("multistage", 0, 2), disk_dir=sys.argv[1])
u0 = torch.ones(4, step.problem.output_size, dtype=torch.float64, requires_grad=True)
kappa = torch.ones(step.problem.control_size("kappa"), dtype=torch.float64, requires_grad=True)  # reads the states
rollout(u0, 3, kappa=kappa)[:, -1].sum().backward()          # forms compiled, nothing limited yet
resource.setrlimit(resource.RLIMIT_FSIZE, (1000, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
try:
    rollout(u0, 3, kappa=kappa)[:, -1].sum().backward()
except OSError as err:
    print(err)
"""


def test_a_multistage_state_that_cannot_be_written_is_named_at_the_write(tmp_path):
    """Under a file-size limit (Python ignores SIGXFSZ, so the write fails with EFBIG) a state once went to
    disk truncated, and the backward failed with "cannot reshape array of size 109"."""
    done = subprocess.run([sys.executable, "-c", FILE_SIZE_LIMIT, str(tmp_path)], capture_output=True, text=True,
                          timeout=300, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"})
    assert done.returncode == 0, done.stderr[-3000:]
    assert "a multistage rollout could not write its state of step 0 to" in done.stdout, done.stdout
    assert "(File too large: a full disk or a file-size limit); free space there" in done.stdout, done.stdout


def test_states_in_memory_are_the_snapshots_and_the_working_pair(lshape):
    """What docs/api/rollout.md says ``most_in_memory`` counts: s + 2 for ("revolve", s), N + 1 for "all",
    where the adjoint reads the states (a kappa gradient); 2 where it reads none (u0's alone)."""
    step = SolveLayer(forms.heat.problem(lshape, controls=("u0", "kappa")), "lu")
    u0 = torch.ones(step.problem.output_size, dtype=torch.float64, requires_grad=True)
    kappa = torch.ones(step.problem.control_size("kappa"), dtype=torch.float64)
    for schedule, expected, wanted in (("all", 13, True), (("revolve", 1), 3, True), (("revolve", 3), 5, True),
                                       (("revolve", 3), 2, False)):
        rollout = Rollout(step, "u0", schedule=schedule)
        rollout(u0, 12, kappa=kappa.clone().requires_grad_(wanted))[-1].sum().backward()
        assert rollout.schedule_stats.most_in_memory == expected, (schedule, rollout.schedule_stats)
        assert rollout.schedule_stats.recomputed == 0 or wanted
    step.close()
