"""The flow scenes: the Burgers emulator chain and the Navier-Stokes neural hybrid.

Tiny versions of the bundled scenes: the chains' gradients against finite
differences, exact iteration counts through the unrolled steps, the
fine-to-coarse point-evaluation transfer, and training that improves on the
untrained (or uncorrected) model.
"""
from __future__ import annotations

from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import mesh
from fempdl.app import scene
from fempdl.app.runs import runner
from fempdl.app.schema import PdeConfig
from fempdl.app.tasks.data import smooth_fields
from fempdl.app.tasks.hybrid import HybridTask, VelocityTransfer, channel_problem
from fempdl.app.tasks.networks import ResidualMLP
from fempdl.ksp_adjoint import KSPOptions

from helpers import tiny_scene

BURGERS = tiny_scene(name="tiny-burgers", mesh={"h": 0.25}, pde={"type": "burgers", "nu": 0.01, "dt": 0.5},
                     data={"train": 8, "rollout": 2}, optimizer={"lr": 3e-3, "epochs": 12, "batch": 4},
                     solver={"preset": "gmres"}, prdp={"dk": 3, "tau_step": None, "adjoint_health": 1.0})

HYBRID = tiny_scene("hybrid")


@pytest.fixture(scope="module")
def burgers():
    return scene.parse(BURGERS)


@pytest.fixture(scope="module")
def hybrid():
    return scene.parse(HYBRID)


def _directional_check(task, loss_fn, eps=1e-6):
    """Autograd's derivative of ``loss_fn()`` along a random direction in every
    parameter against a central difference; returns (autograd, finite difference)."""
    params = list(task.model.parameters())
    gen = torch.Generator().manual_seed(3)
    direction = [torch.randn(p.shape, generator=gen, dtype=p.dtype) for p in params]
    task.model.zero_grad()
    loss_fn().backward()
    exact = sum(float((p.grad * d).sum()) for p, d in zip(params, direction))
    values = []
    with torch.no_grad():
        for sign in (1.0, -1.0):
            for p, d in zip(params, direction):
                p.add_(sign * eps * d)
            values.append(float(loss_fn()))
            for p, d in zip(params, direction):
                p.sub_(sign * eps * d)
    return exact, (values[0] - values[1]) / (2 * eps)


# ------------------------------------------------------------------ pieces
def test_vector_smooth_fields_are_blocked_independent_and_keep_the_scalar_stream():
    coords = np.random.default_rng(0).uniform(0.0, 1.0, size=(50, 3))
    coords[:, 2] = 0.0
    scalar = smooth_fields(coords, 3, 2, np.random.default_rng(5))
    one = smooth_fields(coords, 3, 2, np.random.default_rng(5), components=1)
    assert np.array_equal(scalar, one)
    vector = smooth_fields(coords, 3, 2, np.random.default_rng(5), components=2)
    assert vector.shape == (3, 100)
    x, y = vector[:, 0::2], vector[:, 1::2]
    assert np.abs(x - y).max() > 1e-3  # independent components
    # Sine modes vanish on the bounding box: a node on its edge has zero velocity.
    edge = np.array([[0.0, 0.3, 0.0], [0.2, 0.0, 0.0]])
    assert np.abs(smooth_fields(edge, 2, 3, np.random.default_rng(1), components=2)).max() == 0.0


def test_corrector_starts_at_identity_and_never_moves_masked_dofs():
    mask = torch.tensor([1.0, 0.0, 1.0, 0.0])
    net = ResidualMLP(4, 8, 2, mask=mask, start_at_identity=True)
    u = torch.randn(5, 4)
    assert torch.equal(net(u), u)
    opt = torch.optim.SGD(net.parameters(), lr=0.5)
    for _ in range(3):
        opt.zero_grad()
        (net(u) - 1.0).square().sum().backward()
        opt.step()
    moved = net(u) - u
    assert torch.equal(moved[:, 1::2], torch.zeros(5, 2))
    assert moved[:, 0::2].abs().min() > 1e-3
    with pytest.raises(ValueError, match=r"mask must have shape \(4,\), got \(3,\)"):
        ResidualMLP(4, mask=torch.ones(3))


def test_point_evaluation_transfer_is_exact_for_quadratics_and_fills_boundary_nodes():
    pde = PdeConfig(type="oseen", nu=1e-3, dt=0.02, inflow=1.0, degree=2)
    fine = channel_problem(mesh.load("obstacle", MPI.COMM_SELF, h=0.08), pde, controls=())
    coarse = channel_problem(mesh.load("obstacle", MPI.COMM_SELF, h=0.15), pde, controls=())
    Vf, Vc = fine.field_space("u"), coarse.field_space("u")
    transfer = VelocityTransfer(Vf, Vc)

    def field(space):
        x = space.tabulate_dof_coordinates()[:space.dofmap.index_map.size_local]
        return np.stack([x[:, 1] ** 2 - x[:, 0] * x[:, 1], 0.5 * x[:, 0] ** 2 + x[:, 1]], axis=1).ravel()

    moved = transfer(np.stack([field(Vf), 2.0 * field(Vf)]))
    expected = field(Vc)
    found = np.repeat(transfer.found, 2) * 2 + np.tile([0, 1], len(transfer.found))
    # P2 holds quadratics exactly, so point evaluation inside the fine mesh is exact.
    assert np.abs(moved[0, found] - expected[found]).max() < 1e-12
    assert np.abs(moved[1] - 2.0 * moved[0]).max() < 1e-12
    # Coarse P2 nodes on the cylinder's chords lie in the finer polygon's hole:
    # they exist, are few, and take the nearest fine node's value (close by).
    assert 0 < len(transfer.missing) < 0.05 * len(transfer.points)
    assert np.linalg.norm(transfer.points[transfer.missing, :2] - [0.2, 0.2], axis=1).max() < 0.06
    missing = np.repeat(transfer.missing, 2) * 2 + np.tile([0, 1], len(transfer.missing))
    assert np.abs(moved[0, missing] - expected[missing]).max() < 0.05
    with pytest.raises(ValueError, match=r"values must have shape \(B, \d+\)"):
        transfer(np.ones((2, 7)))


def test_transfer_between_different_domains_is_an_error():
    lshape = mesh.load("lshape", MPI.COMM_SELF, h=0.3)
    from fempdl import forms
    source = forms.burgers.problem(lshape, controls=()).V
    target = channel_problem(mesh.load("obstacle", MPI.COMM_SELF, h=0.15),
                             PdeConfig(type="oseen", nu=1e-3, dt=0.02, inflow=1.0, degree=2),
                             controls=()).field_space("u")
    with pytest.raises(ValueError, match="lie outside the source mesh.*do not cover the same domain"):
        VelocityTransfer(source, target)


# ------------------------------------------------------------------ Burgers emulator
def test_burgers_chain_gradient_matches_finite_differences(burgers):
    task = runner.build_task(burgers, KSPOptions.preset("lu"))
    try:
        task.model.double()
        u0, u2 = task.train_u0[:3].double(), task.train_targets[0, :3].double()
        from fempdl.app.tasks.metrics import nmse
        exact, fd = _directional_check(task, lambda: nmse(task.physics(task.layer, task.model(u0)), u2))
        assert abs(exact - fd) <= 1e-6 * abs(fd) and abs(fd) > 1e-6
    finally:
        task.close()


def test_burgers_validation_rolls_out_and_capped_chain_counts_iterations(burgers):
    task = runner.build_task(burgers, runner.solver_options(burgers, 4))
    try:
        assert len(task.val_targets) == burgers.data.rollout == 2
        assert task.layer.problem.matrix_controls == {"w"}
        task.train_step(torch.arange(4))
        # Four samples, forward and adjoint, each exactly K = 4 GMRES iterations.
        assert task.layer.stats.forward_iterations == task.layer.stats.backward_iterations == 16
        keps = runner.measure_k_eps(task, burgers)
        assert keps > 8
    finally:
        task.close()


def test_burgers_prdp_trains_below_the_untrained_metric_with_fewer_iterations(burgers):
    base = runner.run(burgers, "converged")
    prdp = runner.run(burgers, "prdp", k_eps_value=base.k_eps)
    task = runner.build_task(burgers, runner.solver_options(burgers, 1))
    untrained = task.validate()
    task.close()
    assert base.final_metric < 0.7 * untrained
    assert prdp.final_metric < 0.7 * untrained
    assert prdp.total_iterations < base.total_iterations
    ks = [row["k"] for row in prdp.rows]
    assert ks == sorted(ks) and ks[-1] > 1


# ------------------------------------------------------------------ NS hybrid
@pytest.fixture(scope="module")
def hybrid_lu(hybrid):
    task = HybridTask(hybrid, KSPOptions.preset("lu"))
    yield task
    task.close()


def test_hybrid_reference_shapes_and_the_untrained_hybrid_is_the_coarse_solver(hybrid, hybrid_lu):
    task = hybrid_lu
    n_u = task.problem.control_size("w")
    assert task.train_states.shape == (4, 6, n_u)   # max(steps, rollout) + 1 states
    assert task.val_states.shape == (4, 3, n_u)
    assert torch.isfinite(task.train_states).all()
    # The reference keeps the inflow: the peak speed is about the inflow peak.
    speed = task.train_states[0].reshape(6, -1, 2).norm(dim=-1).max()
    assert 1.2 < float(speed) < 2.5
    # Zero-initialised output layer: validation equals the coarse solver alone, which is off.
    assert task.validate() == pytest.approx(task.uncorrected_metric, rel=1e-6)
    assert task.uncorrected_metric > 1e-5


def test_hybrid_two_step_gradient_matches_finite_differences(hybrid_lu):
    task = hybrid_lu
    task.model.double()
    states = task.train_states[:, :2].double()
    from fempdl.app.tasks.metrics import nmse
    # Move off the zero output layer so both steps' network terms are active.
    with torch.no_grad():
        task.model.net[-1].weight.normal_(0.0, 1e-3, generator=torch.Generator().manual_seed(1))

    def loss():
        predicted = task.advance(task.layer, states[0], 2)
        return nmse(predicted[0], states[1]) + nmse(predicted[1], states[2])
    try:
        exact, fd = _directional_check(task, loss)
    finally:
        task.model.float()
        with torch.no_grad():
            task.model.net[-1].weight.zero_()
    assert abs(exact - fd) <= 1e-5 * abs(fd) and abs(fd) > 1e-8


def test_hybrid_capped_steps_count_and_training_beats_the_coarse_solver(hybrid):
    task = runner.build_task(hybrid, runner.solver_options(hybrid, 3))
    try:
        task.train_step(torch.arange(3))
        # Three samples, two unrolled steps, exactly K = 3 each. The first step's inputs
        # are data (no gradient), so only the second step solves an adjoint.
        assert task.layer.stats.forward_iterations == 18
        assert task.layer.stats.backward_iterations == 9
    finally:
        task.close()
    run = runner.run(hybrid, "converged")
    assert 4 <= run.k_eps <= 60
    assert run.final_metric < 0.9 * task.uncorrected_metric


def test_cli_runs_a_flow_scene_file_with_prdp_and_the_baseline(tmp_path, capsys):
    from fempdl.app import cli
    path = tmp_path / "tiny-hybrid.toml"
    path.write_text(HYBRID)
    assert cli.main(["run", str(path), "--epochs", "2", "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    printed = capsys.readouterr().out
    assert "PRDP" in printed and "K_eps=" in printed
    for run in ("prdp", "converged"):
        assert (tmp_path / "out" / run / "checkpoint.pt").exists()


def test_hybrid_warm_start_begins_at_the_state(hybrid):
    """The capped Oseen step starts from (u_t, 0 pressure): after one iteration its velocity is
    closer to the converged step's than from zero, and the warm-started chain trains."""
    warm_scene = scene.parse(tiny_scene("hybrid", solver={"warm_start": True}))
    cold = runner.build_task(hybrid, runner.solver_options(hybrid, 1))
    warm = runner.build_task(warm_scene, runner.solver_options(warm_scene, 1))
    try:
        u = warm.val_states[0].double()
        start = warm._start(warm.layer, u, None)["initial_guess"]
        velocity = warm.u_dofs.long()
        assert torch.equal(start[:, velocity], u)
        assert torch.count_nonzero(start) == torch.count_nonzero(u)          # pressure 0 at the first step
        assert cold._start(cold.layer, u, None) == {}
        exact = warm.reference(w=u, u_prev=u)[:, velocity]
        errors = [float((task.layer(w=u, u_prev=u, **task._start(task.layer, u, None))[:, velocity] - exact).norm())
                  for task in (cold, warm)]
        assert errors[1] < 0.5 * errors[0]
        warm.train_step(torch.arange(3))
        assert all(torch.isfinite(p.grad).all() for p in warm.model.parameters())
    finally:
        cold.close()
        warm.close()


# ------------------------------------------------------------------ emulator trained over a rollout
def test_an_emulator_trained_over_m_pairs_chains_them_and_its_gradient_is_exact():
    """[data] train_rollout = 3: the loss is the mean nMSE of the three physics states of the chain
    (network, heat step) x 3 from u0 against the converged trajectory, and its gradient in the
    network's parameters matches central differences."""
    from fempdl.app.tasks.metrics import nmse

    sc = scene.parse(tiny_scene("emulator", data={"train_rollout": 3, "rollout": 2}))
    task = runner.build_task(sc, KSPOptions.preset("lu"))
    try:
        task.model.double()
        assert task.train_targets.shape == (3, sc.data.train, task.problem.output_size)
        assert len(task.val_targets) == 2
        idx = torch.arange(3)
        u, errors = task.train_u0[idx].double(), []
        with torch.no_grad():
            for m in range(3):
                u = task.physics(task.reference, task.model(u))
                errors.append(float(nmse(u, task.train_targets[m, idx].double())))
        task.train_u0, task.train_targets = task.train_u0.double(), task.train_targets.double()
        assert abs(float(task.loss(idx).detach()) - np.mean(errors)) <= 1e-12 * np.mean(errors)
        exact, fd = _directional_check(task, lambda: task.loss(idx))
        assert abs(exact - fd) <= 1e-6 * abs(fd) and abs(fd) > 1e-8
    finally:
        task.close()
