"""The batched engine stops where PETSc's KSP stops, and engine="auto" picks the engine the benchmark
found faster (``benchmarks/bench_batched_auto.py``); no test here asserts a time."""
from __future__ import annotations

import warnings

from mpi4py import MPI
import dolfinx.mesh
import numpy as np
import pytest
import torch

from fempdl import forms
from fempdl.bridge_torch import SolveLayer
from fempdl.iterative import sweeps
from fempdl.iterative.batched import BatchedEngine
from fempdl.iterative.sparse import sparse_to_torch
from fempdl.ksp_adjoint import KSPOptions

HUGE = 10 ** 5


def square(cells: int, **kw):
    return forms.poisson.problem(dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, cells, cells), controls=("f",), **kw)


def capped(ksp_type: str, k: int, engine: str) -> KSPOptions:
    return KSPOptions(ksp_type=ksp_type, pc_type="jacobi", max_it=k, engine=engine, on_failure="warn")


def sources(prob, batch: int, seed: int = 0) -> torch.Tensor:
    return torch.from_numpy(np.random.default_rng(seed).standard_normal((batch, prob.control_size("f"))))


def solve_each(prob, options: KSPOptions, F: torch.Tensor) -> list[tuple]:
    """(u, stats) of each row of F solved alone (B = 1: one record per sample)."""
    layer = SolveLayer(prob, options)
    out = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")        # PETSc's own huge-cap solves may end in NaN (checked below)
        for f in F:
            u = layer(f=f)
            out.append((u.detach().numpy(), layer.stats.last))
    return out


# ------------------------------------------------------------------ where a huge cap ends
def test_exactly_zero_residual_stops_at_petsc_count():
    """A zero right-hand side stops CG at its first iteration; on a mesh whose every DOF is a Dirichlet
    DOF (A = I) one step leaves r exactly 0, and KSPCG counts the iteration that finds r.z == 0: 2."""
    prob = square(1, g=lambda x: 1.0 + x[0] * x[1])          # 4 DOFs, all on the boundary
    F = sources(prob, 3)
    F[1] = 0.0
    runs = {e: solve_each(prob, capped("cg", HUGE, e), F) for e in ("petsc", "batched")}
    for (u_p, s_p), (u_b, s_b) in zip(*runs.values()):
        assert (s_b.iterations, s_b.reason_name) == (s_p.iterations, s_p.reason_name) == (2, "CONVERGED_ATOL")
        assert np.array_equal(u_b, u_p)
    zero = square(4)                                          # g = 0: f = 0 gives b = 0
    runs = {e: solve_each(zero, capped("cg", HUGE, e), torch.zeros(1, zero.control_size("f"))) for e in runs}
    for u, stats in (runs["petsc"][0], runs["batched"][0]):
        assert (stats.iterations, stats.reason_name, stats.ok) == (1, "CONVERGED_ATOL", True)
        assert not u.any()


def test_a_batch_with_a_zero_column_counts_as_petsc_does():
    """Columns that run all K and one that stops at once, in one batch: the same counts as PETSc's loop."""
    prob = square(8)
    F = sources(prob, 3)
    F[1] = 0.0
    layers = {e: SolveLayer(prob, capped("cg", 20, e)) for e in ("petsc", "batched")}
    u = {e: layer(f=F) for e, layer in layers.items()}
    assert (u["batched"] - u["petsc"]).abs().max() <= 1e-12 * u["petsc"].abs().max()
    for layer in layers.values():
        assert layer.stats.forward_iterations == 20 + 1 + 20 and layer.stats.failures == 0
    assert layers["batched"].stats.solves_by_engine == {"batched": 3}


def test_huge_cap_cg_ends_where_petsc_ends():
    """10^5 capped CG iterations on 289 unknowns: past convergence the recursive residual shrinks until
    r.z underflows, a few hundred iterations on; both engines stop there (CONVERGED_ATOL) with the same
    solution to round-off. The counts agree to a few percent, not exactly: the last iterations run on
    subnormal numbers whose rounding depends on the order of the sums (PETSc 3.18 and 3.25 disagree by
    as much, and PETSc sometimes goes on into NaN there; the batched CG stops at the first subnormal r.z)."""
    prob = square(16)
    F = sources(prob, 5)
    F[2] = 0.0
    runs = {e: solve_each(prob, capped("cg", HUGE, e), F) for e in ("petsc", "batched")}
    compared = 0
    for i, ((u_p, s_p), (u_b, s_b)) in enumerate(zip(*runs.values())):
        assert s_b.ok and s_b.reason_name == "CONVERGED_ATOL" and s_b.iterations < 1000, (i, s_b)
        if i == 2:
            assert s_b.iterations == s_p.iterations == 1 and not u_b.any()
        elif s_p.ok and s_p.reason_name == "CONVERGED_ATOL":
            assert abs(s_b.iterations - s_p.iterations) <= 0.1 * s_p.iterations, (i, s_b, s_p)
            assert np.abs(u_b - u_p).max() <= 1e-13 * np.abs(u_p).max()
            compared += 1
    assert compared >= 2
    # The whole batch at once, forward and adjoint: both directions end early too.
    layer = SolveLayer(prob, capped("cg", HUGE, "batched"))
    u = layer(f=F.clone().requires_grad_())
    u.sum().backward()
    assert layer.stats.failures == 0
    assert layer.stats.forward_iterations < 5 * 1000 and layer.stats.backward_iterations < 5 * 1000
    assert np.abs(u.detach().numpy() - np.array([r[0] for r in runs["batched"]])).max() <= 1e-13 * u.abs().max()


def test_richardson_fixed_point_is_where_all_k_sweeps_end(monkeypatch):
    """The fused sweeps stop at an exact fixed point; the iterate is bitwise what all K sweeps give."""
    prob = square(8)
    S = SolveLayer(prob, capped("richardson", 1, "petsc")).system.constant_matrix()
    M = sparse_to_torch(sweeps.sweep_matrix(S, 1.0, 1.0 / S.diagonal()))
    c = torch.from_numpy(np.random.default_rng(1).standard_normal((S.shape[0], 3)))
    c[:, 1] = 0.0
    early = sweeps.richardson(M, c, 5000)
    monkeypatch.setattr(sweeps, "FIXED_POINT_CHECK", 10 ** 9)        # no checks: every sweep runs
    assert torch.equal(early, sweeps.richardson(M, c, 5000))
    # Through the layer: PETSc's iterations are all counted, and the results agree.
    F = sources(prob, 3)
    layers = {e: SolveLayer(prob, capped("richardson", HUGE, e)) for e in ("petsc", "batched")}
    u = {e: layer(f=F) for e, layer in layers.items()}
    assert (u["batched"] - u["petsc"]).abs().max() <= 1e-13 * u["petsc"].abs().max()
    assert layers["batched"].stats.forward_iterations == layers["petsc"].stats.forward_iterations == 3 * HUGE


# ------------------------------------------------------------------ the rule of engine="auto"
@pytest.mark.parametrize("batch,ksp_type,k,nnz,want", [
    (128, "cg", 20, 1_889, False),       # 289 unknowns: PETSc's loop is faster at every batch size
    (128, "cg", 200, 1_889, False),
    (128, "cg", None, 7_361, False),     # converged CG, 1089 unknowns
    (8, "cg", 20, 29_057, True),         # 4225 unknowns from B = 8
    (32, "cg", None, 460_289, True),
    (2, "cg", 200, 460_289, False),      # CG below CG_MIN_BATCH
    (2, "richardson", 20, 1_889, False),  # little work per solve: the call's fixed cost dominates
    (2, "richardson", 200, 1_889, False),
    (2, "richardson", 20, 29_057, True),
    (2, "richardson", 200, 7_361, True),
    (8, "richardson", 20, 1_889, True),
    (128, "gmres", 200, 460_289, False),
])
def test_auto_rule(batch, ksp_type, k, nnz, want):
    opts = (KSPOptions.preset("cg", rtol=1e-8) if k is None
            else KSPOptions(ksp_type=ksp_type, pc_type="jacobi", max_it=k))
    assert BatchedEngine.faster_than_petsc(batch, ksp_type, options=opts, nnz=nnz) is want


def test_auto_rule_without_the_matrix_compares_batch_sizes():
    from fempdl.core.tuning import CG_MIN_BATCH, RICHARDSON_MIN_BATCH

    assert BatchedEngine.faster_than_petsc(CG_MIN_BATCH, "cg")
    assert not BatchedEngine.faster_than_petsc(CG_MIN_BATCH - 1, "cg")
    assert BatchedEngine.faster_than_petsc(RICHARDSON_MIN_BATCH, "richardson")
    assert BatchedEngine.faster_than_petsc(2, "richardson", options=capped("richardson", 1, "auto"))


def test_nonzeros_counts_the_pattern_before_assembly():
    prob = square(16)
    layer = SolveLayer(prob, capped("cg", 20, "auto"))
    assert BatchedEngine.nonzeros(layer.system._A) == layer.system.constant_matrix().nnz == 1889


@pytest.mark.parametrize("cells,batch,ksp_type,k,want", [
    (16, 128, "cg", 20, "petsc"),
    (16, 2, "richardson", 20, "petsc"),
    (16, 8, "richardson", 20, "batched"),
    (64, 8, "cg", 20, "batched"),
    (64, 2, "cg", 20, "petsc"),
])
def test_layer_runs_the_engine_the_rule_picks(cells, batch, ksp_type, k, want):
    prob = square(cells)
    layer = SolveLayer(prob, capped(ksp_type, k, "auto"))
    u = layer(f=sources(prob, batch).requires_grad_())
    u.sum().backward()
    assert layer.stats.solves_by_engine == {want: 2 * batch}
    nnz = layer.system.constant_matrix().nnz
    assert BatchedEngine.faster_than_petsc(batch, ksp_type, options=layer.options, nnz=nnz) is (want == "batched")
