"""The marker inverse problem: the rollout P(v0) -> m_T, its gradients and caps, and the Gauss-Newton inverse."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import pytest
import torch
import ufl

from fempdl import mesh
from fempdl.app import scene
from fempdl.app.reports import compare
from fempdl.app.tasks.data import smooth_fields
from fempdl.app.tasks.marker import MarkerInversionTask
from fempdl.app.tasks.marker_rollout import ENCLOSED_LU, MarkerFlow
from fempdl.core import _dolfinx
from fempdl.iterative.batched_cg import matrix_free_cg
from fempdl.ksp_adjoint import KSPOptions
from fempdl.methods.sip import LinearisedGaussNewton

from helpers import tiny_scene


@pytest.fixture(scope="module")
def tiny():
    return MarkerFlow(mesh.load("lshape", MPI.COMM_SELF, h=0.5), steps=2, dt=0.1, nu=0.05, kappa=0.01,
                      smoothing=0.1)


def blob(P: MarkerFlow, centre, width=0.25) -> torch.Tensor:
    return torch.as_tensor(P.transport.interpolate(
        lambda x: np.exp(-((x[0] - centre[0]) ** 2 + (x[1] - centre[1]) ** 2) / (2 * width ** 2))))


def raw_velocity(P: MarkerFlow, count: int, seed: int, speed: float = 1.0) -> torch.Tensor:
    """Smooth random raw velocities scaled so that max |v0| = speed."""
    g = torch.as_tensor(smooth_fields(P.flow.dof_coordinates("u_prev"), count, 3, np.random.default_rng(seed),
                                      components=2))
    top = P.initial_velocity(g).reshape(count, -1, 2).norm(dim=-1).max(dim=1).values
    return g * (speed / top)[:, None]


@pytest.mark.parametrize("wrt", ["g", "m0"])
def test_rollout_gradcheck_with_converged_solves(tiny, wrt):
    g, m0 = raw_velocity(tiny, 2, 0), blob(tiny, (-0.5, 0.3)).repeat(2, 1)
    inputs = {"g": g, "m0": m0}
    assert torch.autograd.gradcheck(lambda x: tiny(**{**inputs, wrt: x}), (inputs[wrt].clone().requires_grad_(),),
                                    eps=1e-6, atol=1e-7, rtol=1e-6)


def test_initial_velocity_is_discretely_divergence_free_and_the_marker_mass_is_kept(tiny):
    g, m0 = raw_velocity(tiny, 1, 1, speed=2.0)[0], blob(tiny, (-0.5, 0.3))
    m_T, velocities, markers = tiny(g, m0, trajectory=True)
    V, Q = tiny.flow.field_space("u"), tiny.flow.field_space("p")
    v_fn = dolfinx.fem.Function(V)
    v_fn.x.array[: tiny.velocity_size] = velocities[0].numpy()
    v_fn.x.scatter_forward()
    q = ufl.TestFunction(Q)
    div = dolfinx.fem.petsc.assemble_vector(_dolfinx.compile_form(q * ufl.div(v_fn) * ufl.dx)).array
    grad = dolfinx.fem.petsc.assemble_vector(_dolfinx.compile_form(
        q * ufl.sqrt(ufl.inner(ufl.grad(v_fn), ufl.grad(v_fn))) * ufl.dx)).array
    assert np.abs(div).max() < 1e-10 * np.abs(grad).max(), (np.abs(div).max(), np.abs(grad).max())
    M = tiny.mass_matrix("marker")
    masses = [float((M @ m.numpy()).sum()) for m in markers]
    np.testing.assert_allclose(masses, masses[0], rtol=1e-12)
    assert float((m_T - m0).norm() / m0.norm()) > 0.05                 # the marker moved


def capped_flow(flow_k: int | None, transport_k: int | None) -> MarkerFlow:
    return MarkerFlow(mesh.load("lshape", MPI.COMM_SELF, h=0.5), steps=2, dt=0.1, nu=0.05, kappa=0.01, smoothing=0.1,
                      flow_options=ENCLOSED_LU if flow_k is None else KSPOptions.preset("schur", max_it=flow_k,
                                                                                       gmres_restart=60),
                      transport_options="lu" if transport_k is None else KSPOptions.preset("gmres-ilu",
                                                                                           max_it=transport_k))


def weighted_gradient(P: MarkerFlow, g, m0) -> torch.Tensor:
    weights = torch.randn(len(g), P.marker_size, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    x = g.clone().requires_grad_(True)
    (P(x, m0) * weights).sum().backward()
    return x.grad


def test_capped_rollout_runs_exactly_k_iterations_per_solve(tiny):
    g, m0 = raw_velocity(tiny, 2, 2), blob(tiny, (-0.5, 0.3))
    capped = capped_flow(5, 5)
    capped.max_it = 2                                   # what PRDP does
    assert [layer.max_it for layer in capped.layers] == [2, 2]
    weighted_gradient(capped, g, m0)
    # 2 samples x 2 steps x K = 2 iterations, forward; the marker's adjoint too (neither converges in 2)
    assert [layer.stats.forward_iterations for layer in capped.layers] == [8, 8]
    assert capped.transport_layer.stats.backward_iterations == 8
    capped.close()


def test_the_capped_marker_steps_gradient_converges_to_the_exact_one(tiny):
    g, m0 = raw_velocity(tiny, 2, 2), blob(tiny, (-0.5, 0.3))
    exact = weighted_gradient(tiny, g, m0)
    capped = capped_flow(None, 2)
    errors = []
    for k in (2, 6, 40):
        capped.transport_layer.max_it = k
        errors.append(float((weighted_gradient(capped, g, m0) - exact).norm() / exact.norm()))
    assert errors[0] > errors[1] > errors[2] and errors[0] > 1e-3 and errors[2] < 1e-10, errors
    capped.close()


def test_moving_the_cap_of_the_schur_flow_step_moves_its_adjoint_cap_too():
    P = capped_flow(2, None)
    g, m0 = raw_velocity(P, 1, 2), blob(P, (-0.5, 0.3))
    weighted_gradient(P, g, m0)                   # the assembled adjoint's KSP is made at cap 2
    before = P.flow_layer.stats.backward_iterations
    assert before == 2 * 2
    P.flow_layer.max_it = 5                       # what PRDP does
    weighted_gradient(P, g, m0)
    assert P.flow_layer.stats.backward_iterations - before == 2 * 5


def test_matrix_free_cg_solves_each_row_on_its_own():
    gen = torch.Generator().manual_seed(1)
    mats = [a @ a.T + 3 * torch.eye(6, dtype=torch.float64)
            for a in torch.randn(3, 6, 6, generator=gen, dtype=torch.float64)]
    rhs = torch.randn(3, 6, generator=gen, dtype=torch.float64)
    dx, iterations = matrix_free_cg(lambda v: torch.stack([m @ r for m, r in zip(mats, v)]), rhs, max_it=50, rtol=1e-13)
    assert iterations <= 7
    torch.testing.assert_close(dx, torch.stack([torch.linalg.solve(m, r) for m, r in zip(mats, rhs)]))


def test_linearised_gauss_newton_on_an_affine_map_is_the_regularised_least_squares_solution():
    gen = torch.Generator().manual_seed(2)
    A = torch.randn(2, 9, 5, generator=gen, dtype=torch.float64)
    c = torch.randn(2, 9, generator=gen, dtype=torch.float64)
    physics = lambda x: torch.einsum("bij,bj->bi", A, x) + c    # noqa: E731
    x0, y = torch.randn(2, 5, generator=gen, dtype=torch.float64), torch.randn(2, 9, generator=gen, dtype=torch.float64)
    beta = 0.1
    x_star = LinearisedGaussNewton(physics, prior=beta, max_it=5)(x0, y)
    for b in range(2):
        expected = torch.linalg.solve(A[b].T @ A[b] + beta * torch.eye(5, dtype=torch.float64), A[b].T @ (y[b] - c[b]))
        torch.testing.assert_close(x_star[b], expected, rtol=1e-5, atol=1e-6)     # the J v forward difference


def test_gauss_newton_reaches_a_marker_error_gradient_descent_does_not_reach_in_many_more_iterations():
    """One inverse problem (h = 0.3, 4 steps): 3 Gauss-Newton steps (10 CG iterations each) against 40 steps of
    gradient descent at its best learning rate of 1, 10, 100 (measured on these problems at h = 0.2)."""
    P = MarkerFlow(mesh.load("lshape", MPI.COMM_SELF, h=0.3), steps=4, dt=0.1, nu=0.01, kappa=0.002, smoothing=0.1)
    g = raw_velocity(P, 1, 1)
    m0 = blob(P, (-0.5, 0.4))[None]
    with torch.no_grad():
        y = P(g, m0)
    prior = 1e-4
    gn = LinearisedGaussNewton(lambda x: P(x, m0), prior=prior, max_it=10)
    x = torch.zeros_like(g)
    gn_errors = []
    for _ in range(3):
        x = gn(x, y)
        gn_errors.append(float(P.relative_error("marker", P(x, m0), y)))
    x = torch.zeros_like(g)
    for _ in range(40):
        x.requires_grad_(True)
        loss = 0.5 * ((P(x, m0) - y) ** 2).sum() + 0.5 * prior * (x ** 2).sum()
        (grad,) = torch.autograd.grad(loss, x)
        x = (x - 10.0 * grad).detach()
    gd_error = float(P.relative_error("marker", P(x, m0), y))
    start = float(P.relative_error("marker", m0, y))
    assert gn_errors[-1] < 0.1 * start and gn_errors[-1] < 0.5 * gd_error, (start, gn_errors, gd_error)
    P.close()


# ------------------------------------------------------------------ the sip-flow scene
# Edits of the tiny sip scene: the marker PDE (2 steps) on a coarse L-shape, Gauss-Newton with 3 CG iterations.
FLOW = {
    "scene": {"name": "tiny-flow"},
    "mesh": {"h": 0.5},
    "pde": {"type": "marker", "dt": 0.1, "nu": 0.05, "kappa": 0.01},
    "marker": {"steps": 2, "width": 0.3},
    "data": {"train": 4, "validation": 3, "modes": 2},
    "network": {"hidden": 16, "layers": 1},
    "sip": {"inverse": "gauss-newton", "cg_iterations": 3},
    "optimizer": {"lr": 1e-3, "epochs": 2, "batch": 4},
}
TINY_FLOW = tiny_scene("sip", FLOW)


def test_the_bundled_sip_flow_scenes_parse_with_the_marker_keys():
    for name in ("sip-flow", "sip-flow-full"):
        sc = scene.load(name)
        assert sc.pde.type == "marker" and sc.pde.degree == 2 and sc.sip.inverse == "gauss-newton"
        assert set(sc.as_dict()["marker"]) == {"steps", "smoothing", "speed", "shape", "width", "placement", "prior",
                                                   "inputs"}
    assert scene.load("sip-poisson").marker is None


@pytest.mark.parametrize("edit, fragment", [
    ({"sip": {"inverse": "exact", "cg_iterations": None}}, "[sip] inverse must be 'gauss-newton' for the marker PDE"),
    ({"pde": {"degree": 1}}, "[pde] degree must be >= 2 for marker"),
    ({"pde": {"type": "poisson", "dt": None, "nu": None, "kappa": None}},
     "[marker] applies to [pde] type 'marker' only"),
    ({"pde": {"theta": 0.5}}, "[pde] theta do(es) not apply to pde 'marker'"),
    ({"marker": {"width": None, "shape": "ring"}}, "[marker] shape must be one of ['blob', 'band']"),
    ({"marker": {"width": None, "inputs": "whitened"}}, "[marker] inputs must be one of ['standardized', 'raw']"),
])
def test_scene_errors_name_the_marker_keys(edit, fragment):
    with pytest.raises(scene.SceneError) as err:
        scene.parse(tiny_scene("sip", FLOW, edit))
    assert fragment in str(err.value)


@pytest.fixture(scope="module")
def tiny_flow_scene():
    return scene.parse(TINY_FLOW)


def test_marker_task_data_and_a_sip_step(tiny_flow_scene):
    task = MarkerInversionTask(tiny_flow_scene, "sip")
    P = task.physics
    assert task.train["inputs"].shape == (4, 2 * P.marker_size) and task.train["g"].shape == (4, P.velocity_size)
    speeds = task.train["v0"].reshape(4, -1, 2).norm(dim=-1).max(dim=1).values
    torch.testing.assert_close(speeds, torch.ones(4, dtype=torch.float64))         # [marker] speed
    torch.testing.assert_close(task.train["y"], P(task.train["g"], task.train["m0"]))
    idx = torch.arange(4)
    x = task.model(task.train["inputs"]).detach()
    x_star = task.inverse(x, task.train["y"], m0=task.train["m0"])
    before = P.relative_error("marker", P(x, task.train["m0"]), task.train["y"])
    after = P.relative_error("marker", P(x_star, task.train["m0"]), task.train["y"])
    assert bool((after < 0.7 * before).all()), (before, after)                  # the inverse's target is better
    first = float(task.loss(idx).detach())
    for _ in range(5):
        task.train_step(idx)
    assert float(task.loss(idx).detach()) < first
    assert task.validation_errors(torch.arange(3)).shape == (3,) and task.marker_errors(torch.arange(3)).shape == (3,)
    task.close()


def test_the_marker_network_standardizes_its_inputs_by_the_first_training_draw(tiny_flow_scene):
    task = MarkerInversionTask(tiny_flow_scene, "backprop")
    standardize, inputs = task.model[0], task.train["inputs"]
    z = standardize(inputs)
    varying = inputs.std(dim=0) >= standardize.scale.max() * 1e-2
    torch.testing.assert_close(z.mean(dim=0), torch.zeros_like(z[0]), atol=1e-12, rtol=0)
    torch.testing.assert_close(z.std(dim=0)[varying], torch.ones(int(varying.sum()), dtype=torch.float64))
    # fixed once built: new training draws and steps leave the statistics alone, and a resumed model
    # (its state_dict into a fresh task) maps inputs exactly as the trained one does
    mean, scale = standardize.mean.clone(), standardize.scale.clone()
    task.start_epoch(1)
    task.train_step(torch.arange(4))
    assert torch.equal(standardize.mean, mean) and torch.equal(standardize.scale, scale)
    resumed = MarkerInversionTask(tiny_flow_scene, "backprop")
    resumed.model.load_state_dict(task.model.state_dict())
    probe = task.val["inputs"]
    assert torch.equal(resumed.model(probe), task.model(probe))
    resumed.close()
    task.close()
    raw = dataclasses.replace(tiny_flow_scene, marker=dataclasses.replace(tiny_flow_scene.marker, inputs="raw"))
    task = MarkerInversionTask(raw, "backprop")
    assert isinstance(task.model[0], torch.nn.Linear)                   # the plain MLP, no input transform
    task.close()


def test_drawing_new_marker_data_counts_no_training_solve(tiny_flow_scene):
    """[data] resample rolls every epoch's truths out through the training layers: those solves are the
    data's, so the counters a run reports (iterations, solves, times) stay where training left them."""
    resampled = dataclasses.replace(tiny_flow_scene, data=dataclasses.replace(tiny_flow_scene.data, resample=True))
    task = MarkerInversionTask(resampled, "backprop")

    def counters():
        return [dataclasses.asdict(layer.stats) for layer in task.layers]

    task.train_step(torch.arange(4))
    trained, y = counters(), task.train["y"]
    assert all(c["forward_solves"] > 0 and c["backward_solves"] > 0 for c in trained)
    task.start_epoch(1)
    assert not torch.equal(task.train["y"], y)                           # new truths were rolled out
    task.marker_errors(torch.arange(3))
    assert counters() == trained
    task.train_step(torch.arange(4))                                     # training still counts
    assert all(after["forward_solves"] == 2 * before["forward_solves"] for after, before in zip(counters(), trained))
    task.close()


def test_compare_runs_sip_flow_against_adam(tiny_flow_scene, tmp_path):
    runs = compare.compare(tiny_flow_scene, tmp_path, max_factor=3)
    split = compare.summary(tiny_flow_scene, runs)
    assert split["method"] == "sip" and split["iterations"] == 2
    assert len(runs["backprop"].rows) >= 2 and split["ratio_equal_iterations"] > 0
    assert all(0 < row["val_metric"] < 2 for r in runs.values() for row in r.rows)


def test_the_benchmark_references_draw_the_training_samples_and_fit_the_truth(tiny_flow_scene):
    """benchmarks/bench_sip_flow.py: the least-squares reference fits the samples the iterations draw, and
    the oracle is the proxy loss against the true velocity, which its steps lower."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    try:
        import bench_sip_flow
    finally:
        sys.path.pop(0)
    reference = bench_sip_flow.least_squares_reference(tiny_flow_scene, iterations=3)
    assert reference["training_samples"] == 3 * tiny_flow_scene.data.train          # one batch per epoch
    assert 0.0 < reference["velocity_error"] < 1.5
    oracle = bench_sip_flow.OracleTask(tiny_flow_scene)
    idx = torch.arange(4)
    with torch.no_grad():
        expected = 0.5 * ((oracle.model(oracle.train["inputs"]) - oracle.train["v0"]) ** 2).sum() / 4
    first = float(oracle.loss(idx).detach())
    assert first == pytest.approx(float(expected), rel=1e-12)
    for _ in range(20):
        oracle.train_step(idx)
    assert float(oracle.loss(idx).detach()) < 0.75 * first
    oracle.close()
