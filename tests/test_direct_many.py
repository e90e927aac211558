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
    calls = []
    original = CappedSolver.solve_many
    monkeypatch.setattr(CappedSolver, "solve_many", lambda self, R: (calls.append(len(R)), original(self, R))[1])
    layer = SolveLayer(prob, "lu")
    out = layer(u0=u0, kappa=kappa)
    assert calls == [5]
    one_by_one = torch.stack([layer(u0=u0[i], kappa=kappa) for i in range(5)])
    assert torch.allclose(out, one_by_one, rtol=0, atol=1e-14)
    assert (layer.stats.forward_solves, layer.stats.forward_iterations) == (10, 10)
    grad = torch.autograd.grad(out.square().sum(), u0)[0]          # the adjoint is unchanged
    reference = SolveLayer(prob, KSPOptions.preset("cg", rtol=1e-13))
    expected = torch.autograd.grad(reference(u0=u0, kappa=kappa).square().sum(), u0)[0]
    assert torch.allclose(grad, expected, rtol=1e-9, atol=1e-12)


def test_solve_many_refuses_iterative_options(coarse_lshape):
    prob = build("poisson", coarse_lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions(max_it=3))
    with pytest.raises(ValueError, match="direct solve"):
        layer.system._solver.solve_many(torch.zeros(2, prob.output_size, dtype=torch.float64).numpy())
