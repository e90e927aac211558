"""Observation operators: point values exact where the space holds the field, mass inner products equal to
the integrals, both linear/bilinear with exact gradients, and clear errors for what they do not support."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl import MassInner, PointObservation, SolveLayer, forms, mesh

F64 = torch.float64
POINTS = np.array([[0.1, 0.2], [-0.5, 0.3], [-0.7, -0.8], [0.0, 0.0], [0.95, 0.05], [-1.0, 1.0]])


@pytest.fixture(scope="module")
def lshape_coarse():
    return mesh.load("lshape", h=0.2)


@pytest.mark.parametrize("degree, field", [(1, lambda x, y: 2 * x - 3 * y + 0.5),
                                           (2, lambda x, y: x ** 2 + 3 * y - x * y)], ids=["P1-linear", "P2-quadratic"])
def test_point_values_are_exact_for_fields_the_space_holds(lshape_coarse, degree, field):
    prob = forms.poisson.problem(lshape_coarse, controls=("f",), degree=degree)
    u = torch.as_tensor(prob.interpolate(lambda x: field(x[0], x[1])))
    observe = PointObservation(prob, POINTS)
    want = torch.as_tensor(field(POINTS[:, 0], POINTS[:, 1]))
    torch.testing.assert_close(observe(u), want, rtol=0, atol=1e-13)
    torch.testing.assert_close(observe(torch.stack([u, 2 * u])), torch.stack([want, 2 * want]), rtol=0, atol=1e-13)
    assert observe.matrix.shape == (len(POINTS), prob.output_size)


def test_observing_a_control_and_a_vector_field(lshape_coarse):
    prob = forms.poisson.problem(lshape_coarse, controls=("f",))
    f = torch.as_tensor(prob.interpolate(lambda x: 1 + x[0], "f"))
    torch.testing.assert_close(PointObservation(prob, POINTS, name="f")(f), torch.as_tensor(1 + POINTS[:, 0]),
                               rtol=0, atol=1e-13)
    burgers = forms.burgers.problem(lshape_coarse, controls=("f",))
    velocity = torch.as_tensor(burgers.interpolate(lambda x: np.stack([x[0], 2 * x[1] - 1]), "f"))
    got = PointObservation(burgers, POINTS[:3], name="f")(velocity)
    want = np.stack([POINTS[:3, 0], 2 * POINTS[:3, 1] - 1], axis=1).reshape(-1)      # point-major
    torch.testing.assert_close(got, torch.as_tensor(want), rtol=0, atol=1e-13)


def test_observation_gradients_through_a_layer_match_finite_differences(lshape_coarse):
    prob = forms.poisson.problem(lshape_coarse, controls=("f",))
    layer, observe = SolveLayer(prob), PointObservation(prob, POINTS[:4])
    f = torch.rand(prob.control_size("f"), dtype=F64, generator=torch.Generator().manual_seed(0))
    assert torch.autograd.gradcheck(lambda g: observe(layer(f=g)), (f.requires_grad_(),))


def test_mass_inner_products_are_the_integrals(lshape_coarse):
    """On the L-shape (area 3): ||1||_L2^2 = 3, and for u = x the H1 square norm is ∫ x^2 + 1 = 1 + 3."""
    prob = forms.poisson.problem(lshape_coarse, controls=("f",))
    one = torch.as_tensor(prob.interpolate(lambda x: np.ones_like(x[0])))
    x = torch.as_tensor(prob.interpolate(lambda x: x[0]))
    l2, h1 = MassInner(prob), MassInner(prob, kind="H1")
    assert float(l2(one)) == pytest.approx(3.0, rel=1e-13)
    assert float(h1(x)) == pytest.approx(4.0, rel=1e-13)          # P1 holds x: exact
    assert float(l2.norm(one)) == pytest.approx(3.0 ** 0.5, rel=1e-13)
    torch.testing.assert_close(l2(torch.stack([one, x]), torch.stack([x, one])), torch.stack([l2(one, x)] * 2))


def test_mass_inner_products_differentiate_exactly(lshape_coarse):
    prob = forms.poisson.problem(lshape_coarse, controls=("f",))
    g = torch.Generator().manual_seed(1)
    u, v = (torch.rand(2, prob.output_size, dtype=F64, generator=g).requires_grad_() for _ in range(2))
    for kind in ("L2", "H1"):
        inner = MassInner(prob, kind=kind)
        assert torch.autograd.gradcheck(lambda a, b, inner=inner: inner(a, b), (u, v))
        assert torch.autograd.gradcheck(lambda a, inner=inner: inner(a), (u,))


def test_what_is_not_supported_is_named(lshape_coarse):
    prob = forms.poisson.problem(lshape_coarse, controls=("f",))
    with pytest.raises(ValueError, match=r"1 point\(s\) lie outside the mesh, e.g. \[0.5, -0.5, 0.0\]"):
        PointObservation(prob, [[0.5, -0.5]])                 # the L-shape's missing quadrant
    with pytest.raises(NotImplementedError, match="Lagrange degree 1 and 2"):
        PointObservation(forms.poisson.problem(lshape_coarse, controls=("f",), degree=3), POINTS)
    with pytest.raises(ValueError, match=r"u must have shape \(\.\.\., \d+\): .* got \(3,\)"):
        PointObservation(prob, POINTS)(torch.zeros(3, dtype=F64))
    with pytest.raises(ValueError, match="kind must be 'L2' or 'H1'"):
        MassInner(prob, kind="H2")


def test_observations_take_any_leading_axes_such_as_a_rollouts_states(lshape_coarse):
    """A heat rollout's states (B, T, n) observed at once: (B, T, N), each time as observed alone; the gradient
    of a weighted sum is the weights times the interpolation matrix, and MassInner reduces (..., n) -> (...)."""
    from fempdl import Rollout

    step = SolveLayer(forms.heat.problem(lshape_coarse, controls=("u0", "f")), "lu")
    prob, observe = step.problem, PointObservation(step.problem, POINTS)
    u0 = torch.as_tensor(prob.interpolate(lambda x: 1 + x[0] * x[1]))
    f = torch.stack([torch.ones(prob.control_size("f"), dtype=F64), -torch.ones(prob.control_size("f"), dtype=F64)])
    states = Rollout(step, "u0")(u0, 3, f=f).detach().requires_grad_()         # (2, 4, n)
    seen = observe(states)
    assert seen.shape == (2, 4, len(POINTS))
    for b in range(2):
        for k in range(4):
            torch.testing.assert_close(seen[b, k], observe(states[b, k]), rtol=0, atol=0)
    weights = torch.rand(2, 4, len(POINTS), dtype=F64, generator=torch.Generator().manual_seed(2))
    (seen * weights).sum().backward()
    torch.testing.assert_close(states.grad, weights @ observe.matrix.to_dense(), rtol=0, atol=1e-14)
    assert torch.autograd.gradcheck(observe, (states[:, :2, :].detach().clone().requires_grad_(),))

    inner = MassInner(prob)
    assert inner(states).shape == (2, 4) and inner.norm(states).shape == (2, 4)
    torch.testing.assert_close(inner(states)[1, 2], inner(states[1, 2]), rtol=1e-14, atol=0)
    # leading axes broadcast: one v for every state, and one u against a batch of v (not only the first)
    torch.testing.assert_close(inner(states, u0), torch.stack([torch.stack([inner(s, u0) for s in row])
                                                               for row in states]), rtol=1e-14, atol=0)
    assert inner(u0, states[:, 0]).shape == (2,)
    torch.testing.assert_close(inner(u0, states[:, 0])[1], inner(u0, states[1, 0]), rtol=1e-14, atol=0)
    n = prob.output_size
    with pytest.raises(ValueError, match=rf"u must have shape \(\.\.\., {n}\): {n} owned DOF values last, e\.g\. "
                                         rf"\(B, {n}\) or a rollout's \(B, T, {n}\); got \(2, 4, {n + 1}\)"):
        observe(torch.zeros(2, 4, n + 1, dtype=F64))
    with pytest.raises(ValueError, match=rf"u \(2, 4, {n}\) and v \(3, {n}\) have leading axes that do not "
                                         "broadcast"):
        inner(states, torch.zeros(3, n, dtype=F64))


def test_rows_of_a_rank_that_owns_no_dofs():
    """A rank of a distributed mesh may own no DOFs: (..., 0) tensors become (prod(...), 0) rows, where
    reshape(-1, 0) is ambiguous and raised while the other ranks waited in the collective product."""
    from fempdl.layer.observation import _rows

    assert _rows(torch.zeros(2, 3, 0), 0).shape == (6, 0)
    assert _rows(torch.zeros(0), 0).shape == (1, 0)
