"""The batched engine: same iterates and gradients as PETSc's KSP, and when it runs."""
from __future__ import annotations

import pytest
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions, SolverFailedError, SolverWarning

from conftest import build, control_values


def jacobi(k, engine, **kw):
    return KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=k, engine=engine, **kw)


def cg(k, engine, **kw):
    return KSPOptions.preset("cg", max_it=k, engine=engine, **kw)


def gmres(k, engine, **kw):
    return KSPOptions.preset("gmres", max_it=k, gmres_restart=7, engine=engine, **kw)


def solve_and_grad(layer, controls, grad_names, weights):
    inputs = {n: t.clone().requires_grad_(n in grad_names) for n, t in controls.items()}
    u = layer(**inputs)
    (u * weights).sum().backward()
    return u.detach(), {n: inputs[n].grad for n in grad_names}


@pytest.mark.parametrize("k", [1, 5, 60])
@pytest.mark.parametrize("solver", ["jacobi", "jacobi-damped", "cg", "gmres"])
@pytest.mark.parametrize("form,grad_names", [("poisson", ("f", "kappa")), ("heat", ("u0", "f", "kappa"))])
def test_batched_engine_matches_petsc(lshape, form, grad_names, k, solver):
    prob = build(form, lshape)
    make = {"jacobi": jacobi, "jacobi-damped": lambda k, e: jacobi(k, e, petsc_options={"ksp_richardson_scale": 0.6}),
            "cg": cg, "gmres": gmres}[solver]
    batched, petsc = (SolveLayer(prob, make(k, e)) for e in ("batched", "petsc"))
    controls = {n: control_values(prob, n, batch=4, seed=i) for i, n in enumerate(grad_names)}
    controls["kappa"] = controls["kappa"][0]          # shared: the matrix is the same for the batch
    w = torch.randn(4, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(5))
    u_b, g_b = solve_and_grad(batched, controls, grad_names, w)
    u_p, g_p = solve_and_grad(petsc, controls, grad_names, w)
    # CG's recurrences amplify round-off a little over 60 iterations.
    tol = 1e-10 if solver in ("cg", "gmres") else 1e-12
    assert (u_b - u_p).abs().max() <= tol * u_p.abs().max()
    for n in grad_names:
        assert (g_b[n] - g_p[n]).abs().max() <= 10 * tol * g_p[n].abs().max(), n
    assert batched.stats.solves_by_engine == {"batched": 8}
    assert petsc.stats.solves_by_engine == {"petsc": 8}
    assert batched.stats.forward_iterations == petsc.stats.forward_iterations == 4 * k


def test_unpreconditioned_richardson_matches_petsc(lshape):
    prob = build("heat", lshape, controls=("u0",))
    opts = dict(ksp_type="richardson", pc_type="none", max_it=7, petsc_options={"ksp_richardson_scale": 300.0})
    u0 = control_values(prob, "u0", batch=3)
    out = [SolveLayer(prob, KSPOptions(**opts, engine=e))(u0=u0) for e in ("batched", "petsc")]
    assert (out[0] - out[1]).abs().max() <= 1e-12 * out[1].abs().max()


def test_engine_choice_per_call(lshape):
    prob = build("poisson", lshape)
    layer = SolveLayer(prob, jacobi(4, "auto"))
    f = control_values(prob, "f", batch=3)
    layer(f=f)
    assert layer.stats.last.engine == "batched"
    layer(f=f[0])                                      # B = 1: nothing to batch
    assert layer.stats.last.engine == "petsc"
    layer(f=f, kappa=control_values(prob, "kappa", batch=3))   # a matrix per sample
    assert layer.stats.last.engine == "petsc"
    layer.max_it = None                               # converged mode: PETSc's KSP
    layer(f=f)
    assert layer.stats.last.engine == "petsc" and layer.stats.last.iterations > 4
    assert layer.stats.solves_by_engine == {"batched": 3, "petsc": 1 + 3 + 3}


def test_engine_batched_refuses_what_it_cannot_run(lshape):
    prob = build("poisson", lshape)
    with pytest.raises(ValueError, match=r"engine='batched' cannot run these options: it implements Richardson, CG and GMRES"):
        SolveLayer(prob, KSPOptions(ksp_type="bcgs", pc_type="jacobi", max_it=5, engine="batched"))
    with pytest.raises(ValueError, match=r"pure iteration cap"):
        SolveLayer(prob, jacobi(5, "batched", rtol=1e-3))
    with pytest.raises(ValueError, match=r"engine must be one of"):
        KSPOptions(engine="gpu")


def test_batched_failure_is_reported_per_sample(lshape):
    prob = build("heat", lshape, controls=("u0",))
    opts = dict(ksp_type="richardson", pc_type="none", max_it=400, petsc_options={"ksp_richardson_scale": 1e4})
    u0 = control_values(prob, "u0", batch=3)
    layer = SolveLayer(prob, KSPOptions(**opts, engine="batched"))
    with pytest.raises(SolverFailedError, match="produced NaN or inf"):
        layer(u0=u0)
    assert layer.stats.failures == 3
    warn = SolveLayer(prob, KSPOptions(**opts, engine="batched", on_failure="warn"))
    with pytest.warns(SolverWarning, match="produced NaN or inf"):
        out = warn(u0=u0)
    assert not torch.isfinite(out).all()
