"""fempdl.methods.prdp.k_eps: the converged cap of a layer, checked against the residuals of its capped iterates."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
from fempdl.methods.k_eps import k_eps
from fempdl.solve.assembly import assemble_scipy


@pytest.fixture(scope="module")
def heat():
    return forms.heat.problem(mesh.load("lshape", h=0.2), controls=("u0",), dt=0.05)


def test_k_eps_is_the_first_cap_whose_residual_reaches_rtol(heat):
    layer = SolveLayer(heat, KSPOptions(max_it=3))
    x = heat.dof_coordinates()
    u0 = torch.from_numpy(np.stack([np.sin(np.pi * x[:, 0]) * np.cos(2 * x[:, 1]), np.exp(x[:, 0] * x[:, 1])]))
    rtol = 1e-6
    keps = k_eps(layer, u0=u0, rtol=rtol)
    assert layer.max_it == 3 and layer.stats.forward_solves == 0          # the layer itself is untouched

    # the system with its Dirichlet rows: identity rows and zero columns, zero boundary values
    A = assemble_scipy(heat.a_form).tolil()
    M = assemble_scipy(heat.rhs_matrix_form("u0"))
    bc = heat.bc_dofs
    A[bc, :] = 0.0
    A[:, bc] = 0.0
    A[bc, bc] = 1.0
    A = A.tocsr()

    def worst_relative_residual(k):
        layer.max_it = k
        u = layer(u0=u0).numpy()
        b = (M @ u0.numpy().T).T
        b[:, bc] = 0.0
        return max(np.linalg.norm(bi - A @ ui) / np.linalg.norm(bi) for ui, bi in zip(u, b))

    assert keps > 3
    assert worst_relative_residual(keps) < rtol <= worst_relative_residual(keps - 1)


def test_k_eps_errors(heat):
    layer = SolveLayer(heat, KSPOptions(max_it=3))
    with pytest.raises(ValueError, match=r"give the inputs to measure K_eps on as keyword arguments, e.g. u0=tensor"):
        k_eps(layer)
    with pytest.raises(ValueError, match=r"layer solves directly \(ksp_type='preonly'\): it has no iteration cap"):
        k_eps(SolveLayer(heat, KSPOptions.preset("lu")), u0=torch.zeros(heat.output_size, dtype=torch.float64))
    with pytest.raises(TypeError, match=r"target must be a SolveLayer, a NonlinearSolveLayer, a NewtonCaps, a Rollout "
                                        r"or a list of them \(or a torch module holding them\), got str"):
        k_eps("layer", u0=None)
