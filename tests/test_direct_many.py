"""Direct solves of a batch that shares its matrix: one factorisation, one MatMatSolve."""
from __future__ import annotations

import pytest
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import CappedSolver, KSPOptions

from helpers import build, control_values


def test_batch_of_direct_solves_equals_one_at_a_time(coarse_lshape, monkeypatch):
    prob = build("heat", coarse_lshape, controls=("u0", "kappa"))
    u0 = control_values(prob, "u0", 5, seed=1).requires_grad_()
    kappa = control_values(prob, "kappa", 1, seed=1)[0]          # shared: one factorisation
    calls = record_solve_many(monkeypatch)
    layer = SolveLayer(prob, "lu")
    out = layer(u0=u0, kappa=kappa)
    assert calls == [(5, False)]
    one_by_one = torch.stack([layer(u0=u0[i], kappa=kappa) for i in range(5)])
    assert torch.allclose(out, one_by_one, rtol=0, atol=1e-14)
    assert (layer.stats.forward_solves, layer.stats.forward_iterations) == (10, 10)
    grad = torch.autograd.grad(out.square().sum(), u0)[0]          # the adjoint: one transposed MatMatSolve
    assert calls[-1] == (5, True) and layer.stats.backward_solves == 5
    reference = SolveLayer(prob, KSPOptions.preset("cg", rtol=1e-13))
    expected = torch.autograd.grad(reference(u0=u0, kappa=kappa).square().sum(), u0)[0]
    assert torch.allclose(grad, expected, rtol=1e-9, atol=1e-12)


def record_solve_many(monkeypatch) -> list:
    """(rows, transpose) of every CappedSolver.solve_many call."""
    calls = []
    original = CappedSolver.solve_many

    def counted(self, R, **kw):
        calls.append((len(R), kw.get("transpose", False)))
        return original(self, R, **kw)
    monkeypatch.setattr(CappedSolver, "solve_many", counted)
    return calls


@pytest.mark.parametrize("symmetric", [True, False])
def test_a_batch_adjoint_by_the_forward_factors_equals_one_sample_at_a_time(coarse_lshape, monkeypatch, symmetric):
    """All samples' transposed solves at once, by the forward's LU: A = A^T (heat) by MatMatSolve, and a
    general A (transport) by KSPMatSolveTranspose where PETSc has it (>= 3.19), else one sample at a time."""
    from fempdl import forms
    from fempdl.core import _dolfinx
    if symmetric:
        prob = build("heat", coarse_lshape, controls=("u0", "kappa"))
        names = ("u0", "kappa")
    else:
        prob = forms.transport.problem(coarse_lshape, controls=("w", "m_prev", "f"), kappa=1e-2, dt=0.05)
        names = ("m_prev", "w")
    batched, shared = names
    x = control_values(prob, batched, 4, seed=2).requires_grad_()
    m = (control_values(prob, shared, 1, seed=3)[0] if symmetric
         else 0.5 * torch.ones(prob.control_size("w"), dtype=torch.float64)).requires_grad_()
    weights = torch.rand(4, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    calls = record_solve_many(monkeypatch)
    layer = SolveLayer(prob, "lu")
    grads = torch.autograd.grad((weights * layer(**{batched: x, shared: m})).sum(), (x, m))
    many = symmetric or hasattr(_dolfinx.PETSc.KSP, "matSolveTranspose")
    assert calls == [(4, False)] + ([(4, True)] if many else [])
    one = [torch.autograd.grad((weights[i] * layer(**{batched: x[i], shared: m})).sum(), (x, m)) for i in range(4)]
    torch.testing.assert_close(grads[0], sum(g[0] for g in one), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(grads[1], sum(g[1] for g in one), rtol=1e-12, atol=1e-14)


def test_solve_many_refuses_iterative_options(coarse_lshape):
    prob = build("poisson", coarse_lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions(max_it=3))
    with pytest.raises(ValueError, match="direct solve"):
        layer.system._solver.solve_many(torch.zeros(2, prob.output_size, dtype=torch.float64).numpy())
