"""Promises the safety page makes and the code now keeps: a positive coefficient passed as a control is
refused before any solve, an unrolled Newton call that cannot fit in memory is refused before its first
step, observations take a nonlinear problem's output, and ranks holding different parameters are told.

Each test fails without its check: a sign-changing kappa solved without a word, an unrolled Newton cap
of 1e8 whose iterates grew without bound, a TypeError for a NonlinearProblem, ranks drifting apart.
"""
from __future__ import annotations

import subprocess
import sys

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import torch
from test_mpi import mpirun

from fempdl import (
    KSPOptions,
    MassInner,
    NewtonOptions,
    NonlinearSolveLayer,
    PointObservation,
    Problem,
    SolveLayer,
    forms,
)
from fempdl.core import _dolfinx, parallel
from fempdl.layer import newton_layer

F64 = torch.float64
LU = NewtonOptions(rtol=1e-12, atol=1e-14, ksp="lu")
POINTS = np.array([[0.1, 0.2], [0.5, 0.5], [0.9, 0.3], [0.25, 0.75]])


@pytest.fixture(scope="module")
def square():
    return dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6)


def sign_changing(prob, name: str = "kappa") -> torch.Tensor:
    """+1 on x >= 0.5, -1 left of it: the sign-changing coefficient a network's raw output gives."""
    x = torch.as_tensor(prob.dof_coordinates(name)[:, 0])
    return torch.where(x < 0.5, -1.0, 1.0).to(F64)


# ------------------------------------------------------------------ positive controls
@pytest.mark.parametrize("module, controls, positive", [
    (forms.poisson, ("f", "kappa"), {"kappa"}),
    (forms.poisson, ("f",), {"kappa"}),                 # the fixed number: a positive Constant
    (forms.heat, ("u0", "kappa"), {"kappa", "dt"}),
    (forms.elasticity, ("f",), {"E"}),
    (forms.elasticity, ("f", "E"), {"E"}),
    (forms.nonlinear_diffusion, ("f", "kappa", "alpha"), {"kappa"}),
    (forms.hyperelasticity, ("E",), {"E"}),
    (forms.navier_stokes, ("f", "nu"), {"nu"}),
], ids=["poisson", "poisson-f", "heat", "elasticity-f", "elasticity", "nonlinear-diffusion", "hyperelasticity",
        "navier-stokes"])
def test_the_bundled_forms_declare_their_positive_controls(square, module, controls, positive):
    assert module.problem(square, controls=controls).positive == frozenset(positive)


def test_a_nonpositive_control_value_is_refused_with_its_count_and_the_fix(square):
    prob = forms.poisson.problem(square, controls=("f", "kappa"))
    kappa = sign_changing(prob)
    bad = int((kappa <= 0).sum())
    with pytest.raises(ValueError, match=rf"control 'kappa' must be > 0 everywhere .* got {bad} value\(s\) <= 0, "
                                         r"the lowest -1; pass a positive map of the network output, e.g. "
                                         r"torch.exp\(out\) or torch.nn.functional.softplus\(out\)"):
        prob.check_control_values("kappa", kappa)
    batch = np.stack([kappa.abs().numpy() + 1, np.arange(len(kappa)) - 2.0])        # -2, -1 and 0 in sample 1
    with pytest.raises(ValueError, match=r"got 3 value\(s\) <= 0, the lowest -2"):
        prob.check_control_values("kappa", batch)
    prob.check_control_values("kappa", kappa.abs() + 1e-300)      # positive, however small
    prob.check_control_values("f", kappa)                          # f may take any sign
    prob.check_control_values("initial_guess", kappa)


def test_positive_names_controls_and_can_be_switched_off(square):
    prob = forms.poisson.problem(square, controls=("f", "kappa"))
    with pytest.raises(ValueError, match=r"positive names \['E'\], which are not among this problem's controls or "
                                         r"Constants \['f', 'kappa'\]"):
        prob.positive = {"E"}
    with pytest.raises(TypeError, match="positive must be a collection of names, got int"):
        prob.positive = 1
    prob.positive = ()
    prob.check_control_values("kappa", sign_changing(prob))        # the user solves such values on purpose
    own = Problem(prob.a, prob.L, prob.bcs, controls={"kappa": prob.control("kappa")}, positive="kappa")
    assert own.positive == {"kappa"} and Problem(prob.a, prob.L, prob.bcs).positive == frozenset()


LAYERS = {
    "linear-implicit": lambda p: SolveLayer(p, "lu"),
    "linear-unrolled": lambda p: SolveLayer(p, KSPOptions.preset("jacobi", max_it=5), diff="unrolled"),
    "newton-implicit": lambda p: NonlinearSolveLayer(p, LU),
    "newton-unrolled": lambda p: NonlinearSolveLayer(p, NewtonOptions(ksp="lu", max_it=2), diff="unrolled"),
}


@pytest.mark.parametrize("kind", list(LAYERS))
def test_every_layer_refuses_a_sign_changing_coefficient_before_solving(square, kind):
    """Each layer solved such a kappa (an LU solve returns a finite u) and said nothing."""
    module = forms.poisson if kind.startswith("linear") else forms.nonlinear_diffusion
    prob = module.problem(square, controls=("f", "kappa"))
    layer = LAYERS[kind](prob)
    f = torch.ones(prob.control_size("f"), dtype=F64)
    with pytest.raises(ValueError, match=r"control 'kappa' must be > 0 everywhere"):
        layer(f=f, kappa=sign_changing(prob))
    assert layer.stats.forward_solves == 0
    assert torch.isfinite(layer(f=f, kappa=sign_changing(prob).abs())).all()     # the layer goes on


# ------------------------------------------------------------------ unrolled Newton memory
def test_an_unrolled_newton_call_beyond_the_memory_budget_is_refused_before_its_first_step(square, monkeypatch):
    prob = forms.nonlinear_diffusion.problem(square, controls=("f",))
    layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=5), diff="unrolled")
    f = torch.ones(2, prob.control_size("f"), dtype=F64)
    needed = 8 * 6 * 2 * prob.output_size                          # (steps + 1) * batch * n float64 values
    monkeypatch.setattr(newton_layer, "memory_budget", lambda: needed - 1)
    with pytest.raises(MemoryError, match=r"would keep .* of iterates for backward \(\(steps \+ 1\) \* batch \* n "
                                          r"float64 values, steps = 5, batch = 2, "
                                          rf"n = {prob.output_size}\), more than half the memory "
                                          r"available now .*; cap Newton lower \(max_it=5\), pass fewer samples"):
        layer(f=f)
    assert layer.stats.newton_steps == 0
    monkeypatch.setattr(newton_layer, "memory_budget", lambda: needed)
    assert layer(f=f).shape == (2, prob.output_size)


UNBOUNDED_CAP = """
from mpi4py import MPI  # before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads
import dolfinx.mesh, torch
from fempdl import NewtonOptions, NonlinearSolveLayer, forms
prob = forms.nonlinear_diffusion.problem(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 6, 6), controls=("f",))
layer = NonlinearSolveLayer(prob, NewtonOptions(ksp="lu", max_it=10**8), diff="unrolled")
try:
    layer(f=torch.ones(prob.control_size("f"), dtype=torch.float64))
except MemoryError as err:
    print(err, layer.stats.newton_steps)
"""


def test_an_unrolled_newton_cap_of_1e8_is_refused_by_the_default_budget():
    """Without a bound the iterates of a 1e8-step cap grew by 3 MiB/s until the machine ran out."""
    done = subprocess.run([sys.executable, "-c", UNBOUNDED_CAP], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "more than half the memory available now" in done.stdout
    assert done.stdout.rstrip().endswith(" 0")                     # no step was taken


# ------------------------------------------------------------------ observing a nonlinear layer
def test_point_observations_of_a_newton_layer_equal_the_function_values(square):
    prob = forms.nonlinear_diffusion.problem(square, controls=("f",))
    f = torch.as_tensor(prob.interpolate(lambda x: 10 + 5 * x[0], "f"))
    u = NonlinearSolveLayer(prob, LU)(f=f)
    fn = prob.to_function(u.detach())
    points = np.pad(POINTS, ((0, 0), (0, 1)))
    found, cells = _dolfinx.point_evaluator(prob.V.mesh, points)
    assert len(found) == len(points)
    want = fn.eval(points, cells)[:, 0]
    torch.testing.assert_close(PointObservation(prob, POINTS)(u), torch.as_tensor(want), rtol=0, atol=1e-13)
    assert float(u.abs().max()) > 0.1


def test_a_gradient_through_mass_inner_of_a_newton_layer(square):
    prob = forms.nonlinear_diffusion.problem(square, controls=("f",))
    layer, energy = NonlinearSolveLayer(prob, LU), MassInner(prob, kind="H1")
    f = torch.as_tensor(prob.interpolate(lambda x: 10 + 5 * x[0], "f")).requires_grad_()
    assert torch.autograd.gradcheck(lambda g: energy(layer(f=g)), (f,), eps=1e-6, atol=1e-6, rtol=1e-5)


# ------------------------------------------------------------------ data-parallel parameters
def test_one_rank_always_holds_the_same_parameters():
    model = torch.nn.Linear(3, 2)
    parallel.check_same_parameters(model, MPI.COMM_SELF)
    with pytest.raises(ValueError, match=r"rtol must be a number in \[0, 1\), got -1"):
        parallel.check_same_parameters(model, MPI.COMM_SELF, rtol=-1)
    fingerprint = parallel.parameter_fingerprint(model.parameters())
    assert fingerprint.shape == (2, 3) and fingerprint[:, 2].tolist() == [6, 2]


def test_a_loop_without_sum_gradients_is_caught_after_one_step(tmp_path):
    done = mpirun(2, "parameter_check.py", timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = dict(line.split(": ", 1) for line in done.stdout.strip().splitlines())
    assert lines["summed"] == "same on both ranks"
    assert lines["forgotten"].startswith("ValueError on both ranks: the ranks hold different parameters: 2 of 2 "
                                         "tensors differ, e.g. 'weight' sums to rank 0: ")
    assert "call parallel.sum_gradients(model.parameters(), comm) after loss.backward()" in lines["forgotten"]
    assert lines["seeds"].startswith("ValueError on both ranks: the ranks hold different parameters")


def test_on_a_distributed_mesh_every_rank_refuses_alike():
    """The budget sums the iterates of a machine's ranks; a kappa <= 0 on one rank is refused on both."""
    done = mpirun(2, "newton_memory.py", timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = dict(line.split(": ", 1) for line in done.stdout.strip().splitlines())
    assert lines["budget"].startswith("MemoryError: an unrolled Newton call would keep ")
    assert "of iterates for backward on the 2 ranks of " in lines["budget"]
    assert lines["steps"] == "0"
    assert lines["kappa"].startswith("ValueError: control 'kappa' must be > 0 everywhere")
    assert "got 2 value(s) <= 0, the lowest -1;" in lines["kappa"]
