"""diff="unrolled": the exact derivative of the K-step iterate, same forward as PETSc's KSP."""
from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import torch

from fempdl.bridge_torch import SolveLayer
from fempdl.iterative import unrolled
from fempdl.iterative.sparse import sparse_to_torch
from fempdl.ksp_adjoint import KSPOptions
from fempdl.layer.unrolled_diff import matrix_jacobian

from helpers import CONVERGED, build, control_values

UNROLLED_SOLVERS = {
    "jacobi": lambda k: KSPOptions(max_it=k),
    "jacobi-damped": lambda k: KSPOptions(max_it=k, petsc_options={"ksp_richardson_scale": 0.7}),
    "cg": lambda k: KSPOptions.preset("cg", max_it=k),
    "gmres": lambda k: KSPOptions.preset("gmres", max_it=k, gmres_restart=4),   # restarts inside K
}
RHS_CONTROLS = [("poisson", "f"), ("heat", "u0"), ("heat", "f")]


def grad_of(layer, name, m, w):
    m = m.clone().requires_grad_()
    (layer(**{name: m}) * w).sum().backward()
    return m.grad


@pytest.mark.parametrize("solver", sorted(UNROLLED_SOLVERS))
@pytest.mark.parametrize("k", [1, 2, 5, 20])
@pytest.mark.parametrize("form,control", RHS_CONTROLS)
def test_unrolled_forward_equals_petsc_and_gradcheck_of_the_capped_map(coarse_problems, form, control, k, solver):
    prob = coarse_problems[form]
    opts = UNROLLED_SOLVERS[solver](k)
    layer = SolveLayer(prob, opts, diff="unrolled")
    petsc = SolveLayer(prob, KSPOptions(**{**opts.__dict__, "engine": "petsc"}))
    m = control_values(prob, control, batch=2)
    u, u_petsc = layer(**{control: m}), petsc(**{control: m})
    assert (u - u_petsc).abs().max() <= 1e-12 * u_petsc.abs().max()
    assert torch.autograd.gradcheck(lambda x: layer(**{control: x}), (m.clone().requires_grad_(),),
                                    eps=1e-6, atol=1e-8, rtol=1e-6)
    assert layer.stats.last.iterations == k and layer.stats.last.engine == "unrolled"


@pytest.mark.parametrize("form,control", RHS_CONTROLS)
def test_jacobi_unrolled_and_implicit_gradients_agree(coarse_problems, form, control):
    prob = coarse_problems[form]
    w = torch.randn(3, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    m = control_values(prob, control, batch=3)
    for k in (1, 6, 30):
        g_unr = grad_of(SolveLayer(prob, KSPOptions(max_it=k), diff="unrolled"), control, m, w)
        g_imp = grad_of(SolveLayer(prob, KSPOptions(max_it=k)), control, m, w)
        assert (g_unr - g_imp).abs().max() <= 1e-12 * g_imp.abs().max()


@pytest.mark.parametrize("preset", ["cg", "gmres"])
def test_krylov_unrolled_and_implicit_differ_at_small_k_and_converge_together(coarse_problems, preset):
    prob = coarse_problems["poisson"]
    f = control_values(prob, "f", batch=1)[0]
    w = torch.linspace(-1, 1, prob.output_size, dtype=torch.float64)
    exact = grad_of(SolveLayer(prob, CONVERGED["lu"]), "f", f, w)
    errors = {}
    for k in (3, 10, 60):
        opts = KSPOptions.preset(preset, max_it=k)
        g_unr = grad_of(SolveLayer(prob, opts, diff="unrolled"), "f", f, w)
        g_imp = grad_of(SolveLayer(prob, opts), "f", f, w)
        errors[k] = (float((g_unr - g_imp).norm() / exact.norm()), float((g_unr - exact).norm() / exact.norm()),
                     float((g_imp - exact).norm() / exact.norm()))
    assert errors[3][0] > 1e-3                                   # two different gradients at a small cap
    assert errors[60][1] < 1e-8 and errors[60][2] < 1e-8         # both exact once CG has converged
    assert errors[10][1] < errors[3][1] and errors[10][2] < errors[3][2]


def test_steepest_descent_matches_its_definition_and_gradcheck():
    """The PRDP paper's Algorithm 2, against a NumPy transcription; gradients of the capped map."""
    rng = np.random.default_rng(0)
    n = 30
    S = sp.diags([-1.0, 2.2, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    R = rng.standard_normal((n, 3))
    X_ref = np.zeros_like(R)
    for j in range(3):
        x, r = np.zeros(n), R[:, j].copy()
        for _ in range(9):
            alpha = (r @ r) / (r @ (S @ r))
            x, r = x + alpha * r, r - alpha * (S @ r)
        X_ref[:, j] = x
    A = sparse_to_torch(S)
    X = unrolled.solve("steepest_descent", A, None, torch.from_numpy(R), 9)
    np.testing.assert_allclose(X.numpy(), X_ref, rtol=1e-12, atol=1e-14)
    Rt = torch.from_numpy(R).requires_grad_()
    assert torch.autograd.gradcheck(lambda r: unrolled.solve("steepest_descent", A, None, r, 9), (Rt,))


@pytest.mark.parametrize("method", ["jacobi", "steepest_descent", "cg", "gmres"])
def test_zero_rhs_and_iterations_past_convergence_stay_finite(method):
    """Zero right-hand sides, and K far past convergence (GMRES: happy breakdown
    within one cycle, then the exact solution), give finite values and gradients."""
    n = 12
    S = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    A, P = sparse_to_torch(S), torch.from_numpy(1.0 / S.diagonal())[:, None]
    R = torch.zeros(n, 2, dtype=torch.float64)
    R[:, 1] = torch.linspace(0, 1, n, dtype=torch.float64)     # column 0 zero, column 1 solved to round-off
    R.requires_grad_()
    X = unrolled.solve(method, A, P, R, 400, restart=100)
    assert torch.all(X[:, 0] == 0)
    exact = np.linalg.solve(S.toarray(), R[:, 1].detach().numpy())
    np.testing.assert_allclose(X[:, 1].detach().numpy(), exact, rtol=1e-10)
    (X ** 2).sum().backward()
    assert torch.isfinite(R.grad).all()
    # Past convergence the VJP is the converged one: 2 A^{-T} x.
    np.testing.assert_allclose(R.grad[:, 1].numpy(), np.linalg.solve(S.toarray().T, 2 * exact), rtol=1e-7)


def test_checkpointing_gives_the_same_gradient(coarse_problems):
    prob = coarse_problems["heat"]
    u0 = control_values(prob, "u0", batch=4)
    w = torch.randn(4, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    opts = KSPOptions.preset("cg", max_it=25)
    full = grad_of(SolveLayer(prob, opts, diff="unrolled"), "u0", u0, w)
    least = unrolled.checkpointed_values("cg", 25, prob.output_size, 4)
    assert unrolled.stored_values("cg", 25, prob.output_size, 4) > least
    bounded = SolveLayer(prob, opts, diff="unrolled", max_unrolled_values=least)
    torch.testing.assert_close(grad_of(bounded, "u0", u0, w), full, rtol=1e-13, atol=1e-15)


@pytest.mark.parametrize("method", ["jacobi", "steepest_descent", "cg", "gmres"])
@pytest.mark.parametrize("matrix_grad", [False, True])
def test_stored_values_bounds_what_autograd_keeps(method, matrix_grad):
    """stored_values is the memory statement users size max_unrolled_values by:
    count the distinct storages autograd saves (saved-tensor hooks) at two K and
    check the per-iteration growth against it; Jacobi on a constant operator keeps none."""
    from fempdl.layer.unrolled_diff import _EntryMatrix
    n, batch = 300, 3
    S = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n)).tocoo()
    rows, cols = torch.from_numpy(S.row.astype(np.int64)), torch.from_numpy(S.col.astype(np.int64))

    def saved_floats(K):
        values = torch.from_numpy(S.data)[:, None].repeat(1, batch).requires_grad_(matrix_grad)
        if matrix_grad:
            A = _EntryMatrix(rows, cols, values, n)
        else:
            from fempdl.iterative.sparse import SparseOperator
            A = SparseOperator.from_scipy(S)
        P = 1.0 / values[rows == cols]
        R = torch.randn(n, batch, dtype=torch.float64, generator=torch.Generator().manual_seed(0)).requires_grad_()
        seen = {}

        def pack(t):
            seen[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes() // 8
            return t
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            unrolled.solve(method, A, P, R, K, restart=5)
        return sum(seen.values())

    growth = saved_floats(30) - saved_floats(10)
    bound = unrolled.stored_values(method, 20, n, batch, matrix_grad=matrix_grad)
    scalars = 20 * 10 * batch                        # step lengths: a few per column and iteration
    assert growth <= bound + scalars
    assert growth >= 0.5 * bound                     # the statement is not a loose overestimate
    if method == "jacobi" and not matrix_grad:
        assert bound == 0 and growth == 0


def test_checkpointing_a_matrix_control_gives_the_same_gradient(coarse_problems):
    prob = coarse_problems["poisson"]
    kappa = control_values(prob, "kappa", batch=3)
    w = torch.randn(3, prob.output_size, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    opts = KSPOptions(max_it=16)
    full = grad_of(SolveLayer(prob, opts, diff="unrolled"), "kappa", kappa, w)
    least = unrolled.checkpointed_values("jacobi", 16, prob.output_size, 3, matrix_grad=True)
    assert unrolled.stored_values("jacobi", 16, prob.output_size, 3, matrix_grad=True) > least
    bounded = SolveLayer(prob, opts, diff="unrolled", max_unrolled_values=least)
    torch.testing.assert_close(grad_of(bounded, "kappa", kappa, w), full, rtol=1e-13, atol=1e-15)


def test_float32_and_unbatched(coarse_problems):
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, KSPOptions(max_it=10), diff="unrolled")
    f = control_values(prob, "f", batch=2)
    f32 = f.float().requires_grad_()
    out = layer(f=f32)
    assert out.dtype == torch.float32 and out.shape == (2, prob.output_size)
    out.sum().backward()
    assert f32.grad.dtype == torch.float32
    torch.testing.assert_close(layer(f=f[0]), layer(f=f)[0], rtol=0, atol=0)


@pytest.mark.parametrize("solver", ["jacobi", "cg", "gmres"])
@pytest.mark.parametrize("k", [1, 12])
@pytest.mark.parametrize("form,other", [("poisson", "f"), ("heat", "u0")])
def test_unrolled_matrix_control_gradcheck_and_forward(coarse_problems, form, other, k, solver):
    """kappa enters the matrix: the entries are an exact affine function of it (J),
    and autograd through the K iterations with per-sample matrices is the exact VJP."""
    prob = coarse_problems[form]
    opts = UNROLLED_SOLVERS[solver](k)
    layer = SolveLayer(prob, opts, diff="unrolled")
    kappa = control_values(prob, "kappa", batch=2)
    m = control_values(prob, other, batch=2)
    u = layer(**{other: m, "kappa": kappa})
    u_petsc = SolveLayer(prob, KSPOptions(**{**opts.__dict__, "engine": "petsc"}))(**{other: m, "kappa": kappa})
    assert (u - u_petsc).abs().max() <= 1e-12 * u_petsc.abs().max()
    assert torch.autograd.gradcheck(lambda a, b: layer(**{other: a, "kappa": b}),
                                    (m.requires_grad_(), kappa.requires_grad_()), eps=1e-6, atol=1e-8, rtol=1e-6)


@pytest.mark.parametrize("form", ["poisson-p2-dg0", "heat"])
def test_matrix_jacobian_reproduces_the_assembled_matrix(coarse_lshape, form):
    from fempdl.core import matrices
    from fempdl.solve.petsc import petsc_to_scipy
    prob = build(form, coarse_lshape)
    layer = SolveLayer(prob, KSPOptions(max_it=3))
    pattern, v0, J = matrix_jacobian(layer.system, "kappa")
    kappa = control_values(prob, "kappa", batch=1)[0].numpy()
    fn = prob.control("kappa")
    fn.x.array[: len(kappa)] = kappa
    A = matrices.create_matrix(prob.a_form)
    matrices.assemble_matrix_into(A, prob.a_form, prob.bcs)
    S = petsc_to_scipy(A)
    assert np.array_equal(S.indices, pattern.indices)
    np.testing.assert_allclose(v0 + J @ kappa, S.data, rtol=0, atol=1e-13 * np.abs(S.data).max())
    assert J.shape == (S.nnz, prob.control_size("kappa")) and J.nnz < 40 * prob.control_size("kappa")


def test_what_unrolled_mode_refuses(coarse_problems, coarse_lshape):
    prob = coarse_problems["poisson"]
    with pytest.raises(ValueError, match=r"diff='unrolled' supports .*got bcgs\+jacobi"):
        SolveLayer(prob, KSPOptions(ksp_type="bcgs", pc_type="jacobi", max_it=5), diff="unrolled")
    with pytest.raises(ValueError, match="pure cap"):
        SolveLayer(prob, KSPOptions(max_it=5, rtol=1e-6), diff="unrolled")
    lifted = build("poisson", coarse_lshape, g=1.0)
    with pytest.raises(NotImplementedError, match=r"needs zero Dirichlet values"):
        SolveLayer(lifted, KSPOptions(max_it=5), diff="unrolled")(kappa=control_values(lifted, "kappa", batch=2))
    theta_half = coarse_problems["heat-cn"]                       # kappa also in the right-hand side
    with pytest.raises(NotImplementedError, match=r"absent from the right-hand side"):
        SolveLayer(theta_half, KSPOptions(max_it=5), diff="unrolled")(kappa=control_values(theta_half, "kappa", 2))


@pytest.mark.parametrize("pc,omega", [("jacobi", 1.0), ("jacobi", 0.7), ("none", 0.3)])
def test_linear_richardson_on_a_constant_operator_matches_the_step_recurrence(pc, omega):
    """On a constant SparseOperator, Richardson runs as fused sweeps X <- c + M X with a K-sweep
    adjoint (one autograd node); forward and gradient equal autograd through the steps
    X <- X + omega P (R - A X), which a plain torch matrix still takes."""
    from fempdl.iterative.sparse import SparseOperator
    rng = np.random.default_rng(0)
    n, K = 40, 17
    S = sp.diags([-1.0, 2.5, -1.2], [-1, 0, 1], shape=(n, n), format="csr") + sp.diags(rng.random(n))
    P = torch.from_numpy(1.0 / S.diagonal())[:, None] if pc == "jacobi" else None
    R = torch.from_numpy(rng.standard_normal((n, 3))).requires_grad_()
    W = torch.from_numpy(rng.standard_normal((n, 3)))
    fused = unrolled.solve("jacobi", SparseOperator.from_scipy(S), P, R, K, omega=omega)
    steps = unrolled.solve("jacobi", sparse_to_torch(S), P, R, K, omega=omega)
    assert len(_nodes(fused)) == 2 and len(_nodes(steps)) > K      # the map's node and R's accumulator
    torch.testing.assert_close(fused, steps, rtol=1e-13, atol=1e-15)
    g_fused, = torch.autograd.grad((fused * W).sum(), R)
    g_steps, = torch.autograd.grad((steps * W).sum(), R)
    torch.testing.assert_close(g_fused, g_steps, rtol=1e-13, atol=1e-15)
    assert torch.autograd.gradcheck(
        lambda r: unrolled.solve("jacobi", SparseOperator.from_scipy(S), P, r, K, omega=omega), (R,))


def _nodes(t):
    seen, todo = set(), [t.grad_fn]
    while todo:
        fn = todo.pop()
        if fn is not None and fn not in seen:
            seen.add(fn)
            todo += [nxt for nxt, _ in fn.next_functions]
    return seen


@pytest.mark.parametrize("pc", ["jacobi", "none"])
@pytest.mark.parametrize("K", [1, 7, 60])
def test_reverse_cg_on_a_constant_operator_matches_autograd_through_the_steps(pc, K):
    """CG on a constant SparseOperator runs with a hand-written reverse pass; its forward and
    gradient equal autograd through the recurrences (a plain torch matrix), checkpointed or
    not, with a zero column and K past convergence (n = 40)."""
    from fempdl.iterative.sparse import SparseOperator
    rng = np.random.default_rng(1)
    n = 40
    S = sp.diags([-1.0, 2.5, -1.2], [-1, 0, 1], shape=(n, n), format="csr") + sp.diags(rng.random(n))
    S = (S + S.T).tocsr()
    P = torch.from_numpy(1.0 / S.diagonal())[:, None] if pc == "jacobi" else None
    R = torch.from_numpy(rng.standard_normal((n, 3)))
    R[:, 1] = 0.0
    R.requires_grad_()
    W = torch.from_numpy(rng.standard_normal((n, 3)))
    steps = unrolled.solve("cg", sparse_to_torch(S), P, R, K)
    g_steps, = torch.autograd.grad((steps * W).sum(), R)
    least = unrolled.checkpointed_values("cg", K, n, 3)
    for max_values in (None, least):
        op = SparseOperator.from_scipy(S)
        X = unrolled.solve("cg", op, P, R, K, max_values=max_values)
        assert type(X.grad_fn).__name__ == "ConstantOperatorCGBackward"
        torch.testing.assert_close(X, steps, rtol=1e-12, atol=1e-14)
        g, = torch.autograd.grad((X * W).sum(), R)
        torch.testing.assert_close(g, g_steps, rtol=1e-10, atol=1e-13)
        assert torch.all(X[:, 1] == 0) and torch.isfinite(g).all()
    # Checkpointed (K = 30 stores more than its least bound), away from the zero column's branch.
    R_live = torch.from_numpy(rng.standard_normal((n, 2))).requires_grad_()
    least = unrolled.checkpointed_values("cg", 30, n, 2)
    assert unrolled.stored_values("cg", 30, n, 2) > least
    assert torch.autograd.gradcheck(lambda r: unrolled.solve("cg", SparseOperator.from_scipy(S), P, r, 30,
                                                             max_values=least), (R_live,))


@pytest.mark.parametrize("scale", [1e-100, 1e100])
def test_reverse_cg_gradient_does_not_depend_on_the_scale_of_the_right_hand_side(scale):
    """X_K(s R) = s X_K(R), so the gradient of W.X_K at s R is the one at R; no square of a step
    quantity may overflow or underflow on the way (it did with beta^2 and gamma^2)."""
    from fempdl.iterative.sparse import SparseOperator
    rng = np.random.default_rng(2)
    n = 30
    S = sp.diags([-1.0, 2.5, -1.0], [-1, 0, 1], shape=(n, n), format="csr")
    P = torch.from_numpy(1.0 / S.diagonal())[:, None]
    R = torch.from_numpy(rng.standard_normal((n, 2)))
    W = torch.from_numpy(rng.standard_normal((n, 2)))
    grads = []
    for s in (1.0, scale):
        x = (s * R).requires_grad_()
        (unrolled.solve("cg", SparseOperator.from_scipy(S), P, x, 12) * W).sum().backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-12, atol=0)


def test_second_derivatives_through_constant_operator_solves():
    """The constant-operator paths (Richardson's linear map, whose adjoint is the same map with
    M^T; CG's reverse pass, which falls back to autograd through the steps under create_graph)
    give the Hessian-vector products of autograd through the steps, also when the loss depends
    on R by another path too."""
    from fempdl.iterative.sparse import SparseOperator
    rng = np.random.default_rng(3)
    n = 20
    S = sp.diags([-1.0, 2.5, -1.3], [-1, 0, 1], shape=(n, n), format="csr")
    P = torch.from_numpy(1.0 / S.diagonal())[:, None]
    R0, V = (torch.from_numpy(rng.standard_normal((n, 2))) for _ in range(2))

    def hvp(method, A):
        R = R0.clone().requires_grad_()
        loss = (unrolled.solve(method, A, P, R, 9, omega=0.8) ** 3).sum() + (R ** 3).sum()
        g, = torch.autograd.grad(loss, R, create_graph=True)
        return torch.autograd.grad((g * V).sum(), R)[0]
    for method in ("jacobi", "cg"):
        torch.testing.assert_close(hvp(method, SparseOperator.from_scipy(S)), hvp(method, sparse_to_torch(S)),
                                   rtol=1e-12, atol=1e-13)
