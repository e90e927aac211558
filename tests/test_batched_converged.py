"""Batched CG to a tolerance: each column stops where PETSc's KSPCG would, with its iterations,
reason and failures reported per sample, forward and adjoint."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions, SolverFailedError, SolverWarning

from helpers import build, control_values

RTOL = 1e-8


def recorded(layer) -> list:
    """Every (direction, SolveStats) the layer's stats receive, in order (one per sample)."""
    seen = []
    record = layer.stats.record
    layer.stats.record = lambda direction, stats: (seen.append((direction, stats)), record(direction, stats))
    return seen


def sources(prob, batch: int) -> torch.Tensor:
    """Mixed columns: random sources at several scales and smoothness (different iteration
    counts), and a zero source (a zero right-hand side: 0 iterations)."""
    f = control_values(prob, "f", batch=batch, seed=3)
    f[1] = 1.0
    f[2] *= 1e-6
    f[batch - 1] = 0.0
    return f


def run(layer, f, w):
    f = f.clone().requires_grad_()
    u = layer(f=f)
    (u * w).sum().backward()
    return u.detach(), f.grad


def test_columns_stop_where_petsc_stops_and_agree_within_the_tolerance(lshape):
    """Per-sample iterations and reasons, forward and adjoint, against one KSP solve per sample.

    Iterations: a count is where the computed dp_k = ||P r_k|| first falls to ttol; the engines
    compute the same dp_k up to round-off (their sums run in other orders), so a count can move
    only when some dp_k lies within round-off of ttol: then by one step (the next dp_k is below
    ttol in both unless the preconditioned residual rises again, which needs the same tie). One
    step either way is allowed.

    Values: each engine stops with ||P r|| <= rtol ||P b||, so its error is
    ||x - x*|| <= ||(PA)^-1|| rtol ||P A x*|| <= cond(PA) rtol ||x*||; the two differ by at most
    twice that. Gradients dJ/df = C^T lam with lam from the adjoint solve: bounded the same way
    through ||C||. cond(PA) and ||C|| are computed from the dense matrices of this small problem."""
    prob = build("poisson", lshape, controls=("f",))
    batch = 8
    f = sources(prob, batch)
    w = torch.randn(batch, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    w[batch - 1] = 0.0                                # a zero adjoint right-hand side too
    out, seen = {}, {}
    for engine in ("batched", "petsc"):
        layer = SolveLayer(prob, KSPOptions.preset("cg", rtol=RTOL, engine=engine))
        seen[engine] = recorded(layer)
        out[engine] = run(layer, f, w)
        assert layer.stats.solves_by_engine == {engine: 2 * batch}
    pairs = list(zip(seen["batched"], seen["petsc"]))
    assert [d for (d, _), _ in pairs] == ["forward"] * batch + ["backward"] * batch
    for (_, got), (_, want) in pairs:
        assert abs(got.iterations - want.iterations) <= 1
        assert got.reason_name == want.reason_name and got.ok and not got.capped
    assert pairs[batch - 1][0][1].iterations == 0 and pairs[-1][0][1].iterations == 0
    counts = [st.iterations for (_, st), _ in pairs[:batch - 1]]
    assert len(set(counts)) > 1                        # columns really stop at different steps

    S = SolveLayer(prob, KSPOptions.preset("lu")).system
    A = S.constant_matrix().toarray()
    C = S.affine_rhs(frozenset({"f"}))[1]["f"]
    PA = A / np.diag(A)[:, None]
    cond = np.linalg.cond(PA)
    (u_b, g_b), (u_p, g_p) = out["batched"], out["petsc"]
    bound_u = 2 * cond * RTOL * u_p.norm(dim=1) * (1 + cond * RTOL)
    assert ((u_b - u_p).norm(dim=1) <= bound_u).all()
    lam = torch.from_numpy(np.linalg.solve(A.T, np.where(np.isin(np.arange(A.shape[0]), prob.bc_dofs)[None],
                                                         0.0, w.numpy()).T).T)
    bound_g = 2 * cond * RTOL * np.linalg.norm(C.toarray(), 2) * lam.norm(dim=1)
    assert ((g_b - g_p).norm(dim=1) <= bound_g).all()


def test_a_cap_with_rtol_stops_each_column_at_the_first_of_the_two(lshape):
    """max_it with rtol: a column reaching the cap is capped (no failure), one converging earlier stops there."""
    prob = build("poisson", lshape, controls=("f",))
    f = sources(prob, 4)
    full = SolveLayer(prob, KSPOptions.preset("cg", rtol=RTOL, engine="batched"))
    its = [st.iterations for _, st in (lambda s: (full(f=f), s)[1])(recorded(full))]
    cap = max(its) - 1                               # the hardest column is capped, the zero one is not
    layers = {e: SolveLayer(prob, KSPOptions.preset("cg", rtol=RTOL, max_it=cap, engine=e))
              for e in ("batched", "petsc")}
    seen = {e: recorded(layer) for e, layer in layers.items()}
    u = {e: layer(f=f) for e, layer in layers.items()}
    for (_, got), (_, want) in zip(seen["batched"], seen["petsc"]):
        assert (got.iterations, got.capped, got.ok) == (want.iterations, want.capped, True)
    assert any(st.capped for _, st in seen["batched"]) and not all(st.capped for _, st in seen["batched"])
    # Capped columns stop after the same steps: their iterates agree to round-off.
    assert (u["batched"] - u["petsc"]).abs().max() <= 1e-9 * u["petsc"].abs().max()


def test_gradcheck_through_batched_converged_cg(coarse_lshape):
    prob = build("poisson", coarse_lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions.preset("cg", rtol=1e-13, engine="batched"))
    f = control_values(prob, "f", batch=2).requires_grad_()
    assert torch.autograd.gradcheck(lambda m: layer(f=m), (f,), eps=1e-6, atol=1e-7, rtol=1e-6)
    assert layer.stats.solves_by_engine.keys() == {"batched"}


def test_a_failing_column_fails_as_petsc_and_leaves_the_others(lshape):
    """kappa = -1: A is negative definite on the interior and the identity on the Dirichlet rows.
    A column whose residual stays interior (zero warm start) converges; one whose warm start puts
    a residual on the boundary rows meets p.Ap of both signs: DIVERGED_INDEFINITE_MAT, in both engines."""
    prob = build("poisson", lshape, controls=("f", "kappa"))
    prob.positive = ()          # kappa = -1 on purpose
    f = control_values(prob, "f", batch=3)
    kappa = -torch.ones(prob.control_size("kappa"), dtype=torch.float64)
    x0 = torch.zeros(3, prob.output_size, dtype=torch.float64)
    x0[1, prob.bc_dofs] = 1.0
    messages, values = {}, {}
    for engine in ("batched", "petsc"):
        opts = KSPOptions.preset("cg", pc_type="none", rtol=RTOL, engine=engine)
        with pytest.raises(SolverFailedError,
                           match=r"stopped with DIVERGED_INDEFINITE_MAT after \d+ iterations") as err:
            SolveLayer(prob, opts)(f=f, kappa=kappa, initial_guess=x0)
        messages[engine] = str(err.value).split(" (residual norm")[0]
        warn = SolveLayer(prob, KSPOptions.preset("cg", pc_type="none", rtol=RTOL, engine=engine, on_failure="warn"))
        seen = recorded(warn)
        with pytest.warns(SolverWarning, match="DIVERGED_INDEFINITE_MAT"):
            values[engine] = warn(f=f, kappa=kappa, initial_guess=x0)
        assert [st.ok for _, st in seen] == [True, False, True]
    assert messages["batched"] == messages["petsc"]
    ok = [0, 2]
    assert ((values["batched"][ok] - values["petsc"][ok]).norm(dim=1).max()
            <= 1e-6 * values["petsc"][ok].norm(dim=1).max())


def test_auto_runs_converged_cg_batched_from_the_measured_batch(lshape):
    from fempdl.core.tuning import CG_MIN_BATCH

    prob = build("poisson", lshape, controls=("f",))
    layer = SolveLayer(prob, KSPOptions.preset("cg", rtol=RTOL))
    f = control_values(prob, "f", batch=CG_MIN_BATCH)
    layer(f=f)
    assert layer.stats.last.engine == "batched" and layer.stats.last.reason_name == "CONVERGED_RTOL"
    layer(f=f[:CG_MIN_BATCH - 1])
    assert layer.stats.last.engine == "petsc"
    gmres = SolveLayer(prob, KSPOptions.preset("gmres", rtol=RTOL))
    gmres(f=f)
    assert gmres.stats.last.engine == "petsc"
    with pytest.raises(ValueError, match="only CG also runs to a tolerance"):
        SolveLayer(prob, KSPOptions.preset("gmres", rtol=RTOL, engine="batched"))
