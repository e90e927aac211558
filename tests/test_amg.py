"""The "amg" preset: CG + algebraic multigrid, with adjoints that match LU's to the solve's tolerance."""
from __future__ import annotations

from mpi4py import MPI
import pytest
import torch
from petsc4py import PETSc

from fempdl import mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

from helpers import build, control_values


@pytest.fixture(scope="module")
def poisson():
    return build("poisson", mesh.load("lshape", MPI.COMM_WORLD, h=0.1))


def test_amg_preset_is_cg_with_boomeramg_or_gamg():
    opts = KSPOptions.preset("amg")
    assert opts.ksp_type == "cg"
    expected = "hypre" if PETSc.Sys.hasExternalPackage("hypre") else "gamg"
    assert opts.pc_type == expected
    # hypre's transpose is wrong in PETSc 3.18: the adjoint solves an assembled A^T instead.
    assert opts.assembled_adjoint == (expected == "hypre")


@pytest.mark.parametrize("control", ["f", "kappa"])
def test_amg_gradients_match_lu(poisson, control):
    """Forward solution and the gradient of a quadratic loss agree with LU's to the rtol."""
    x = control_values(poisson, control, batch=3)
    weights = torch.linspace(0.5, 1.5, poisson.output_size, dtype=torch.float64)
    grads, outs = {}, {}
    for preset in ("amg", "lu"):
        opts = KSPOptions.preset(preset, rtol=1e-12) if preset == "amg" else KSPOptions.preset("lu")
        layer = SolveLayer(poisson, opts)
        xi = x.clone().requires_grad_(True)
        u = layer(**{control: xi})
        (weights * u ** 2).sum().backward()
        grads[preset], outs[preset] = xi.grad, u.detach()
        if preset == "amg":
            stats = layer.stats
            assert 0 < stats.max_forward_iterations < 60      # multigrid: a few tens of CG iterations
            assert stats.backward_solves == 3
        layer.close()
    scale = outs["lu"].abs().max()
    assert (outs["amg"] - outs["lu"]).abs().max() < 1e-9 * scale
    assert (grads["amg"] - grads["lu"]).abs().max() < 1e-8 * grads["lu"].abs().max()


def test_amg_iterations_grow_far_slower_than_jacobis(poisson):
    """On two mesh sizes CG + AMG's iteration count stays nearly flat where CG + Jacobi's grows with 1/h."""
    counts = {}
    for h in (0.1, 0.05):
        prob = build("poisson", mesh.load("lshape", MPI.COMM_WORLD, h=h), controls=("f",))
        f = control_values(prob, "f", batch=1)
        for preset in ("amg", "cg"):
            layer = SolveLayer(prob, KSPOptions.preset(preset, rtol=1e-8))
            with torch.no_grad():
                layer(f=f)
            counts[preset, h] = layer.stats.max_forward_iterations
            layer.close()
    assert counts["amg", 0.05] <= counts["amg", 0.1] + 4
    assert counts["cg", 0.05] > 1.5 * counts["cg", 0.1]
    assert counts["amg", 0.05] < counts["cg", 0.05] / 2
