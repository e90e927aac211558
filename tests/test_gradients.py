"""Gradients of SolveLayer: exact where they must be, convergent where they are approximate.

Three layers (DESIGN.md): float64 gradcheck and Taylor tests on converged solves
for every control of every form; the capped Jacobi implicit gradient equals the
derivative of the capped map itself (right-hand-side controls); the capped
GMRES implicit gradient is not that derivative but converges to the exact
gradient as max_it grows.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.core import matrices
from fempdl.ksp_adjoint import KSPOptions

from helpers import CAPPED, CONVERGED, FORM_CONTROL_PAIRS, build, control_values


def layer_fn(layer, name, fixed=None):
    return lambda m: layer(**{name: m}, **(fixed or {}))


@pytest.mark.parametrize("solver", sorted(CONVERGED))
@pytest.mark.parametrize("form,control", FORM_CONTROL_PAIRS)
def test_gradcheck_converged(coarse_problems, form, control, solver):
    # Converged solves: the implicit gradient is the exact gradient of the discrete
    # solution, so full float64 gradcheck (every Jacobian entry against central
    # differences) must pass.
    prob = coarse_problems[form]
    layer = SolveLayer(prob, CONVERGED[solver])
    m = control_values(prob, control, batch=2).requires_grad_()
    assert torch.autograd.gradcheck(layer_fn(layer, control), (m,), eps=1e-6, atol=1e-7, rtol=1e-5)


@pytest.mark.parametrize("form,control", FORM_CONTROL_PAIRS)
def test_taylor_remainder_is_second_order(coarse_problems, form, control):
    """|J(m + h dm) - J(m) - h dJ.dm| = O(h^2) for J = 1/2 ||u - d||^2."""
    prob = coarse_problems[form]
    layer = SolveLayer(prob, CONVERGED["lu"])
    m = control_values(prob, control, batch=1, seed=3)[0].requires_grad_()
    dm = 0.3 * control_values(prob, control, batch=1, seed=4)[0]
    d = torch.linspace(0, 1, prob.output_size, dtype=torch.float64)

    def J(x):
        return 0.5 * ((layer(**{control: x}) - d) ** 2).sum()

    J0 = J(m)
    J0.backward()
    slope = float((m.grad * dm).sum())
    hs = [1e-1 / 2 ** i for i in range(4)]
    with torch.no_grad():
        remainders = [abs(float(J(m + h * dm) - J0) - h * slope) for h in hs]
    rates = np.log2(np.array(remainders[:-1]) / np.array(remainders[1:]))
    assert np.all(rates > 1.9), (remainders, rates)


@pytest.mark.parametrize("engine", ["petsc", "batched"])
@pytest.mark.parametrize("form,control", [("poisson", "f"), ("heat", "u0"), ("heat", "f")])
@pytest.mark.parametrize("k", [1, 4, 25])
def test_capped_jacobi_gradient_is_the_derivative_of_the_capped_map(coarse_problems, form, control, k, engine):
    # For Richardson + Jacobi the transposed K-step solve is the exact VJP of the
    # K-step map with respect to b, so gradcheck of the *capped* map passes.
    prob = coarse_problems[form]
    layer = SolveLayer(prob, KSPOptions(max_it=k, engine=engine))
    m = control_values(prob, control, batch=2).requires_grad_()
    assert torch.autograd.gradcheck(layer_fn(layer, control), (m,), eps=1e-6, atol=1e-8, rtol=1e-6)
    s = layer.stats
    assert s.forward_iterations == k * s.forward_solves and s.backward_iterations == k * s.backward_solves
    assert s.backward_solves > 0 and set(s.solves_by_engine) == {engine}


def gradient(layer, name, m, weights):
    m = m.clone().requires_grad_()
    (layer(**{name: m}) * weights).sum().backward()
    return m.grad


def test_capped_gmres_gradient_converges_to_the_exact_one(coarse_problems):
    prob = coarse_problems["poisson"]
    f = control_values(prob, "f", batch=1)[0]
    w = torch.linspace(-1, 1, prob.output_size, dtype=torch.float64)
    exact = gradient(SolveLayer(prob, CONVERGED["lu"]), "f", f, w)
    errors = []
    for k in (2, 5, 10, 20, 40):
        g = gradient(SolveLayer(prob, CAPPED["gmres"](k)), "f", f, w)
        errors.append(float((g - exact).norm() / exact.norm()))
    assert errors[0] > 1e-2, errors                       # far off at a tiny cap ...
    assert all(b <= 1.05 * a for a, b in zip(errors, errors[1:])), errors
    assert errors[-1] < 1e-6, errors                      # ... and exact once converged


def test_capped_gmres_gradient_is_not_the_derivative_of_the_capped_map(coarse_problems):
    # Documented semantics: GMRES is nonlinear in b, so the implicit gradient of a
    # capped GMRES solve differs from the capped map's own derivative at small K.
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, CAPPED["gmres"](3))
    f = control_values(prob, "f", batch=1)[0]
    w = torch.linspace(-1, 1, prob.output_size, dtype=torch.float64)
    g = gradient(layer, "f", f, w)
    df = control_values(prob, "f", batch=1, seed=7)[0]
    eps = 1e-6
    with torch.no_grad():
        fd = float(((layer(f=f + eps * df) - layer(f=f - eps * df)) * w).sum()) / (2 * eps)
    assert abs(float((g * df).sum()) - fd) > 1e-3 * abs(fd)


def test_float32_inputs_give_float32_outputs_and_gradients(coarse_problems):
    prob = coarse_problems["heat"]
    layer = SolveLayer(prob, CAPPED["jacobi"](10))
    u0 = control_values(prob, "u0", batch=3)
    u0_32 = u0.float().requires_grad_()
    out32 = layer(u0=u0_32)
    assert out32.dtype == torch.float32
    out64 = layer(u0=u0.float().double())
    torch.testing.assert_close(out32.double(), out64, rtol=1e-6, atol=1e-6)
    out32.sum().backward()
    assert u0_32.grad.dtype == torch.float32 and torch.isfinite(u0_32.grad).all()


def test_heat_rollout_gradient(coarse_problems):
    """Three chained heat steps u0 -> u3 with a shared kappa: gradcheck of the rollout."""
    prob = coarse_problems["heat"]
    layer = SolveLayer(prob, CONVERGED["lu"])

    def rollout(u0, kappa):
        u = u0
        for _ in range(3):
            u = layer(u0=u, kappa=kappa)
        return u

    u0 = control_values(prob, "u0", batch=2).requires_grad_()
    kappa = control_values(prob, "kappa", batch=1)[0].requires_grad_()
    assert torch.autograd.gradcheck(rollout, (u0, kappa), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_shared_control_gradient_is_the_sum_over_the_batch(coarse_problems):
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, CONVERGED["lu"])
    f = control_values(prob, "f", batch=3)
    kappa = control_values(prob, "kappa", batch=1)[0].requires_grad_()
    w = torch.randn(3, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    (layer(f=f, kappa=kappa) * w).sum().backward()
    total = torch.zeros_like(kappa)
    for i in range(3):
        k = kappa.detach().clone().requires_grad_()
        (layer(f=f[i], kappa=k) * w[i]).sum().backward()
        total += k.grad
    torch.testing.assert_close(kappa.grad, total, rtol=1e-10, atol=1e-12)


def test_iteration_accounting_follows_max_it(coarse_problems):
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, CAPPED["jacobi"](5))
    f = control_values(prob, "f", batch=4).requires_grad_()
    layer(f=f).sum().backward()
    layer.max_it = 12
    layer(f=f).sum().backward()
    s = layer.stats
    assert (s.forward_iterations, s.backward_iterations) == (4 * 5 + 4 * 12, 4 * 5 + 4 * 12)
    assert (s.forward_solves, s.backward_solves) == (8, 8)
    assert s.total_iterations == 136 and s.solve_time > 0 and s.layer_time >= s.solve_time


def test_only_what_the_call_needs_is_assembled(coarse_lshape, monkeypatch):
    """f-only calls assemble A once for all samples and calls; the kappa
    gradient form is compiled only when a kappa gradient is requested."""
    prob = build("poisson", coarse_lshape)
    layer = SolveLayer(prob, CAPPED["jacobi"](5))
    calls = []
    original = matrices.assemble_matrix_into
    monkeypatch.setattr(matrices, "assemble_matrix_into",
                        lambda A, form, *a, **k: (calls.append(form), original(A, form, *a, **k))[1])
    f = control_values(prob, "f", batch=4).requires_grad_()
    for _ in range(3):
        layer(f=f).sum().backward()
    matrix_assemblies = [c for c in calls if c is prob.a_form]
    assert len(matrix_assemblies) == 1
    assert "kappa" not in prob._gradient_forms
    kappa = control_values(prob, "kappa", batch=4)  # passed, but no grad requested
    layer(f=f, kappa=kappa).sum().backward()
    assert "kappa" not in prob._gradient_forms
    assert len([c for c in calls if c is prob.a_form]) == 1 + 4  # per sample in forward; backward copies them
    shared_kappa = kappa[0].clone().requires_grad_()                   # one kappa for the whole batch
    layer(f=f, kappa=shared_kappa).sum().backward()
    # Once in forward; the backward finds A still holding shared_kappa's matrix and reuses it.
    assert len([c for c in calls if c is prob.a_form]) == 1 + 4 + 1
    assert "kappa" in prob._gradient_forms


def test_matrix_cache_is_not_stale_after_matrix_control_calls(coarse_lshape):
    prob = build("poisson", coarse_lshape)
    fresh = build("poisson", coarse_lshape)
    layer, reference = SolveLayer(prob, CAPPED["jacobi"](7)), SolveLayer(fresh, CAPPED["jacobi"](7))
    f = control_values(prob, "f", batch=2)
    before = layer(f=f)
    layer(f=f, kappa=5.0 * control_values(prob, "kappa", batch=2))
    torch.testing.assert_close(layer(f=f), before, rtol=0, atol=0)
    torch.testing.assert_close(layer(f=f), reference(f=f), rtol=0, atol=0)
    prob.control("kappa").x.array[:] *= 2.0       # a user edit of the fixed coefficient is seen
    torch.testing.assert_close(layer(f=f), reference(f=f) / 2.0, rtol=1e-12, atol=1e-14)


def test_control_functions_are_restored_after_a_call(coarse_problems):
    prob = coarse_problems["heat"]
    before = {n: prob.control(n).x.array.copy() for n in prob.control_names}
    layer = SolveLayer(prob, CAPPED["jacobi"](3))
    u0 = control_values(prob, "u0", batch=2).requires_grad_()
    kappa = control_values(prob, "kappa", batch=2).requires_grad_()
    layer(u0=u0, kappa=kappa).sum().backward()
    for n in prob.control_names:
        np.testing.assert_array_equal(prob.control(n).x.array, before[n])


def test_unbatched_call_matches_batched(coarse_problems):
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, CAPPED["gmres"](8))
    f = control_values(prob, "f", batch=3)
    kappa = control_values(prob, "kappa", batch=3)
    batched = layer(f=f, kappa=kappa)
    assert batched.shape == (3, prob.output_size)
    for i in range(3):
        single = layer(f=f[i], kappa=kappa[i])
        assert single.shape == (prob.output_size,)
        torch.testing.assert_close(single, batched[i], rtol=0, atol=0)


def test_dirichlet_values_are_kept_and_have_no_gradient(coarse_lshape):
    prob = build("poisson", coarse_lshape, g=lambda x: 1.0 + x[0])
    layer = SolveLayer(prob, CONVERGED["lu"])
    kappa = control_values(prob, "kappa", batch=1)[0].requires_grad_()
    u = layer(kappa=kappa)
    xy = prob.dof_coordinates()
    np.testing.assert_allclose(u.detach().numpy()[prob.bc_dofs], 1.0 + xy[prob.bc_dofs, 0], rtol=1e-12)
    # The lifting term makes the interior depend on kappa through the boundary data.
    assert torch.autograd.gradcheck(lambda k: layer(kappa=k), (kappa,), eps=1e-6, atol=1e-7, rtol=1e-5)


def test_in_place_changes_before_backward_are_caught(coarse_problems):
    """backward re-assembles with u and kappa: changing either in place must raise, not corrupt."""
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, CONVERGED["lu"])
    kappa = control_values(prob, "kappa", batch=2).requires_grad_()
    u = layer(kappa=kappa)
    u.mul_(2.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        u.sum().backward()
    k = kappa * 1.0
    u = layer(kappa=k)
    k.mul_(2.0)
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        u.sum().backward()


def test_dirichlet_on_named_boundary_parts(lshape):
    """Dirichlet data on the 'outer' tag only: the reentrant edges are natural (zero flux)."""
    whole = build("poisson", lshape, controls=("f",))
    outer = build("poisson", lshape, controls=("f",), dirichlet=("outer",), g=2.0)
    assert 0 < len(outer.bc_dofs) < len(whole.bc_dofs)
    u = SolveLayer(outer, CONVERGED["lu"])(f=control_values(outer, "f", batch=1)[0])
    np.testing.assert_allclose(u.numpy()[outer.bc_dofs], 2.0, rtol=1e-13)
    xy = outer.dof_coordinates()
    on_reentrant = np.flatnonzero((np.abs(xy[:, 0]) < 1e-12) & (xy[:, 1] < -0.1) & (xy[:, 1] > -0.9))
    assert len(on_reentrant) and np.all(np.abs(u.numpy()[on_reentrant] - 2.0) > 1e-3)
