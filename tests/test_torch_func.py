"""SolveLayer (implicit mode) under torch.func and torch.compile.

torch.func.grad / vjp / jacrev give autograd's gradient (and central differences
agree); vmap maps onto the layer's native batch (one solve call, not one per
sample); torch.compile sees each solve as one opaque operator (no graph break)
and gives eager's value and gradient.
"""
from __future__ import annotations

import pytest
import torch

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer

F64 = torch.float64


@pytest.fixture(scope="module")
def prob():
    return forms.poisson.problem(mesh.load("lshape", h=0.2), controls=("f", "kappa"), kappa=1.0)


@pytest.fixture
def layer(prob):
    lay = SolveLayer(prob, "lu")
    yield lay
    lay.close()


@pytest.fixture
def calls(layer):
    """Batch sizes of the layer's forward and adjoint calls into its LinearSystem."""
    record = {"solve": [], "adjoint": []}
    system = layer.system
    solve, adjoint = system.solve, system.adjoint

    def spy_solve(controls, batch, *a, **k):
        record["solve"].append(batch)
        return solve(controls, batch, *a, **k)

    def spy_adjoint(controls, U, G, *a, **k):
        record["adjoint"].append(G.shape[0])
        return adjoint(controls, U, G, *a, **k)

    system.solve, system.adjoint = spy_solve, spy_adjoint
    return record


def rand(*shape, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(*shape, generator=g, dtype=F64)


def sizes(prob):
    return prob.control_size("f"), prob.control_size("kappa"), prob.output_size


def test_grad_matches_autograd_and_finite_differences(prob, layer):
    nf, nk, n = sizes(prob)
    f, kappa, d = rand(nf, seed=1), 1.0 + rand(nk, seed=2), rand(n, seed=3)

    def J(f, kappa):
        return 0.5 * ((layer(f=f, kappa=kappa) - d) ** 2).sum()

    gf, gk = torch.func.grad(J, argnums=(0, 1))(f, kappa)
    fr, kr = f.clone().requires_grad_(), kappa.clone().requires_grad_()
    af, ak = torch.autograd.grad(J(fr, kr), (fr, kr))
    torch.testing.assert_close(gf, af, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(gk, ak, rtol=1e-12, atol=1e-14)
    assert gf.abs().max() > 1e-3 and gk.abs().max() > 1e-3
    # Central differences along random directions (LU: the discrete gradient is exact).
    h = 1e-5
    for x, g, shift in ((f, gf, lambda s: (f + s, kappa)), (kappa, gk, lambda s: (f, kappa + s))):
        dx = rand(x.shape[0], seed=7) - 0.5
        with torch.no_grad():
            fd = (J(*shift(h * dx)) - J(*shift(-h * dx))) / (2 * h)
        assert abs(float(fd) - float((g * dx).sum())) <= 1e-7 * max(1.0, abs(float(fd)))


def test_vjp_matches_autograd(prob, layer):
    nf, nk, n = sizes(prob)
    f, kappa, w = rand(2, nf, seed=1), 1.0 + rand(nk, seed=2), rand(2, n, seed=4)
    u, vjp = torch.func.vjp(lambda f, k: layer(f=f, kappa=k), f, kappa)
    vf, vk = vjp(w)
    fr, kr = f.clone().requires_grad_(), kappa.clone().requires_grad_()
    ur = layer(f=fr, kappa=kr)
    af, ak = torch.autograd.grad(ur, (fr, kr), w)
    torch.testing.assert_close(u, ur.detach(), rtol=0, atol=0)
    torch.testing.assert_close(vf, af, rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(vk, ak, rtol=1e-12, atol=1e-14)
    assert vk.shape == (nk,)  # the shared kappa collects both samples


def test_jacrev_is_one_batched_adjoint(prob, layer, calls):
    nf, _, n = sizes(prob)
    f = rand(nf, seed=5)
    Jac = torch.func.jacrev(lambda f: layer(f=f))(f)
    assert Jac.shape == (n, nf)
    assert calls["adjoint"] == [n]      # all n rows of the Jacobian in one adjoint call
    # u is linear in f: the Jacobian reproduces the solution and matches autograd's vjp.
    fr = f.clone().requires_grad_()
    u = layer(f=fr)
    torch.testing.assert_close(Jac @ f, u.detach(), rtol=1e-10, atol=1e-12)
    w = rand(n, seed=6)
    g, = torch.autograd.grad(u, fr, w)
    torch.testing.assert_close(Jac.T @ w, g, rtol=1e-10, atol=1e-12)


def test_vmap_is_one_native_batched_call(prob, layer, calls):
    nf, nk, _ = sizes(prob)
    F, kappa = rand(5, nf, seed=1), 1.0 + rand(nk, seed=2)
    U = torch.func.vmap(lambda f: layer(f=f, kappa=kappa))(F)
    assert calls["solve"] == [5]
    ref = layer(f=F, kappa=kappa)
    assert U.shape == ref.shape == (5, prob.output_size)
    torch.testing.assert_close(U, ref, rtol=1e-13, atol=1e-13)
    # Vmapping both controls, and a vmapped dimension over an already batched input.
    K = 1.0 + rand(5, nk, seed=3)
    calls["solve"].clear()
    U = torch.func.vmap(lambda f, k: layer(f=f, kappa=k))(F, K)
    assert calls["solve"] == [5]
    torch.testing.assert_close(U, layer(f=F, kappa=K), rtol=1e-13, atol=1e-13)
    F3 = rand(4, 2, nf, seed=8)
    calls["solve"].clear()
    U3 = torch.func.vmap(lambda f: layer(f=f, kappa=kappa), in_dims=1)(F3)   # vmapped dim 2, native batch 4
    assert calls["solve"] == [8]
    torch.testing.assert_close(U3, layer(f=F3.transpose(0, 1).reshape(8, nf), kappa=kappa).reshape(2, 4, -1))


def test_per_sample_gradients_by_vmap_of_grad(prob, layer, calls):
    nf, nk, n = sizes(prob)
    F, kappa, d = rand(3, nf, seed=1), 1.0 + rand(nk, seed=2), rand(n, seed=3)

    def J(f, k):
        return 0.5 * ((layer(f=f, kappa=k) - d) ** 2).sum()

    gF, gK = torch.func.vmap(torch.func.grad(J, argnums=(0, 1)), in_dims=(0, None))(F, kappa)
    assert calls["solve"] == [3] and calls["adjoint"] == [3]
    for i in range(3):
        fr, kr = F[i].clone().requires_grad_(), kappa.clone().requires_grad_()
        af, ak = torch.autograd.grad(J(fr, kr), (fr, kr))
        torch.testing.assert_close(gF[i], af, rtol=1e-12, atol=1e-14)
        torch.testing.assert_close(gK[i], ak, rtol=1e-12, atol=1e-14)


def test_checks_still_raise_under_transforms(prob, layer):
    nf, nk, _ = sizes(prob)
    F = torch.ones(3, nf, dtype=F64)
    F[1, 2] = float("nan")
    with pytest.raises(ValueError, match=r"control 'f' contains 1 NaN/inf value\(s\)"):
        torch.func.vmap(lambda f: layer(f=f))(F)
    f = torch.ones(nf, dtype=F64)
    with pytest.raises(ValueError, match=r"gradient.*NaN"):
        torch.func.grad(lambda f: (layer(f=f) * float("nan")).sum())(f)


@pytest.mark.parametrize("transform", ["jvp", "jacfwd", "hessian"])
def test_forward_mode_is_refused_by_name(prob, layer, transform):
    """The derivative is an adjoint (reverse mode); the layer has no forward-mode rule (one would keep
    torch.compile from tracing it whole), so forward mode stops with PyTorch's error, as documented."""
    f, kappa = torch.ones(sizes(prob)[0], dtype=F64), torch.ones(sizes(prob)[1], dtype=F64)
    loss = lambda x: (layer(f=x, kappa=kappa) ** 2).sum()  # noqa: E731
    run = {"jvp": lambda: torch.func.jvp(loss, (f,), (f,)), "jacfwd": lambda: torch.func.jacfwd(loss)(f),
           "hessian": lambda: torch.func.hessian(loss)(f)}[transform]
    with pytest.raises(NotImplementedError, match="jvp function .* forward mode AD"):
        run()


def test_compile_is_one_opaque_op_and_matches_eager(prob, layer):
    nf, _, _ = sizes(prob)
    torch.manual_seed(0)
    net = torch.nn.Linear(nf, nf).double()

    def model(f):
        return (layer(f=net(f)) ** 2).sum()

    f = rand(2, nf, seed=1)
    explained = torch._dynamo.explain(model)(f)
    assert explained.graph_break_count == 0 and explained.graph_count == 1
    # The autograd.Function's forward and backward bodies are subgraphs: one operator each.
    code = "\n".join(m.code for m in explained.graphs[0].modules() if hasattr(m, "code"))
    assert code.count("fempdl.implicit_solve") == 1 and code.count("fempdl.implicit_adjoint") == 1
    assert "petsc" not in code.lower() and "scipy" not in code and "numpy" not in code
    torch._dynamo.reset()

    fe = f.clone().requires_grad_()
    ve = model(fe)
    ge_f, ge_w = torch.autograd.grad(ve, (fe, net.weight))
    compiled = torch.compile(model, fullgraph=True)     # inductor (a C++ compiler is present)
    fc = f.clone().requires_grad_()
    vc = compiled(fc)
    gc_f, gc_w = torch.autograd.grad(vc, (fc, net.weight))
    torch.testing.assert_close(vc, ve, rtol=1e-12, atol=0)
    torch.testing.assert_close(gc_f, ge_f, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(gc_w, ge_w, rtol=1e-10, atol=1e-12)
    # A second call with new values reuses the compiled graph.
    f2 = rand(2, nf, seed=2)
    torch.testing.assert_close(compiled(f2), model(f2), rtol=1e-12, atol=0)
    torch._dynamo.reset()


def test_a_layer_built_inline_lives_until_its_backward(prob, layer):
    """The graph keeps the layer: SolveLayer(p)(...) with no other owner still differentiates,
    and gives the gradient of a layer that is kept."""
    import gc

    nf, nk, _ = sizes(prob)
    kappa = 1.0 + rand(nk, seed=4)
    f_inline, f_kept = (rand(nf, seed=5).requires_grad_(True) for _ in range(2))
    loss = (SolveLayer(prob, "lu")(f=f_inline, kappa=kappa) ** 2).sum()
    gc.collect()
    loss.backward()
    (layer(f=f_kept, kappa=kappa) ** 2).sum().backward()
    assert torch.allclose(f_inline.grad, f_kept.grad, rtol=1e-12, atol=0)
