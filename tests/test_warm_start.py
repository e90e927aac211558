"""Warm-started capped solves: K iterations from a given initial guess, and its derivative.

The K-step Richardson + Jacobi map x_K = M^K x0 + (sum_j M^j) D^-1 b, M = I - D^-1 A,
is affine in x0, and its transpose applied to dJ/du is the adjoint residual
dJ/du - A^T lam: the implicit backward gives it exactly, on PETSc and on the
batched engine. Unrolled mode differentiates any method through autograd.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from fempdl import forms
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

from helpers import CAPPED, build, control_values


@pytest.fixture(scope="module")
def heat(coarse_lshape):
    return build("heat", coarse_lshape, controls=("u0", "kappa"))


def _inputs(prob, batch=3, seed=0):
    gen = torch.Generator().manual_seed(seed)
    u0 = control_values(prob, "u0", batch, seed).requires_grad_()
    x0 = torch.randn(batch, prob.output_size, generator=gen, dtype=torch.float64, requires_grad=True)
    return u0, x0


@pytest.mark.parametrize("engine", ["petsc", "batched"])
@pytest.mark.parametrize("diff", ["implicit", "unrolled"])
def test_jacobi_warm_start_gradcheck(heat, engine, diff):
    """The capped Jacobi map is differentiated exactly in its control and its start, both modes."""
    layer = SolveLayer(heat, KSPOptions(max_it=4, engine=engine), diff=diff)
    u0, x0 = _inputs(heat)
    assert torch.autograd.gradcheck(lambda a, b: layer(u0=a, initial_guess=b), (u0, x0))


def test_implicit_equals_unrolled_jacobi(heat):
    u0, x0 = _inputs(heat, seed=1)
    grads = []
    for diff in ("implicit", "unrolled"):
        layer = SolveLayer(heat, KSPOptions(max_it=5, engine="petsc"), diff=diff)
        out = layer(u0=u0, initial_guess=x0)
        grads.append(torch.autograd.grad(out.square().sum(), (u0, x0)))
    for g_imp, g_unr in zip(*grads):
        assert torch.allclose(g_imp, g_unr, rtol=1e-12, atol=1e-14)
    assert grads[0][1].abs().max() > 1e-3          # the start matters at K = 5


@pytest.mark.parametrize("method", ["cg", "gmres"])
def test_krylov_warm_start_matches_petsc_and_gradchecks_unrolled(heat, method):
    """A warm-started Krylov solve is PETSc's nonzero-guess iterate; unrolled differentiates it exactly."""
    u0, x0 = _inputs(heat, seed=2)
    petsc = SolveLayer(heat, CAPPED[method](3))
    unrolled = SolveLayer(heat, CAPPED[method](3), diff="unrolled")
    with torch.no_grad():
        a, b = petsc(u0=u0, initial_guess=x0), unrolled(u0=u0, initial_guess=x0)
    assert torch.allclose(a, b, rtol=1e-10, atol=1e-12)
    assert torch.autograd.gradcheck(lambda a, b: unrolled(u0=a, initial_guess=b), (u0, x0))


def test_warm_start_runs_exactly_k_iterations_and_helps(coarse_lshape):
    """From the state being advanced (a short heat step of smooth states that vanish on
    the boundary), K iterations land closer to the converged step than from zero."""
    heat = forms.heat.problem(coarse_lshape, controls=("u0",), dt=0.002)
    u0 = torch.stack([torch.as_tensor(heat.interpolate(
        lambda x, k=k: np.sin(k * np.pi * (x[0] + 1) / 2) * np.sin(np.pi * (x[1] + 1) / 2), "u0"))
        for k in (1, 2, 3, 4)])
    exact = SolveLayer(heat, "lu")(u0=u0)
    layer = SolveLayer(heat, KSPOptions(max_it=3, engine="petsc"))
    cold = layer(u0=u0)
    warm = layer(u0=u0, initial_guess=u0)
    assert layer.stats.forward_iterations == 2 * 4 * 3
    assert (warm - exact).norm() < 0.7 * (cold - exact).norm()


def test_implicit_start_gradient_vanishes_as_cg_converges(heat):
    """For capped CG the adjoint residual is an approximation; it goes to 0 with K."""
    u0, x0 = _inputs(heat, seed=4)
    sizes = []
    for k in (2, 8, 40):
        layer = SolveLayer(heat, CAPPED["cg"](k))
        out = layer(u0=u0, initial_guess=x0)
        sizes.append(float(torch.autograd.grad(out.square().sum(), x0)[0].norm()))
    assert sizes[0] > sizes[1] > sizes[2] and sizes[2] < 1e-6 * sizes[0]


def test_direct_solve_ignores_the_guess(heat):
    u0, x0 = _inputs(heat, seed=5)
    layer = SolveLayer(heat, "lu")
    out = layer(u0=u0, initial_guess=x0)
    assert torch.allclose(out, layer(u0=u0), rtol=0, atol=1e-13)
    assert torch.count_nonzero(torch.autograd.grad(out.sum(), x0)[0]) == 0


def test_shared_guess_and_matrix_control(heat):
    """A (n,) guess is shared by the batch (its gradient sums the samples); kappa in the matrix."""
    u0 = control_values(heat, "u0", 2, seed=6)
    kappa = control_values(heat, "kappa", 2, seed=6)
    x0 = torch.randn(heat.output_size, dtype=torch.float64, requires_grad=True)
    layer = SolveLayer(heat, KSPOptions(max_it=3))
    assert torch.autograd.gradcheck(lambda b: layer(u0=u0, kappa=kappa, initial_guess=b), (x0,))


def test_bad_guess_is_refused(heat):
    layer = SolveLayer(heat, KSPOptions(max_it=3))
    u0 = control_values(heat, "u0", 2)
    with pytest.raises(ValueError, match="initial_guess"):
        layer(u0=u0, initial_guess=torch.zeros(2, heat.output_size + 1, dtype=torch.float64))
    with pytest.raises(ValueError, match="initial_guess.*NaN"):
        layer(u0=u0, initial_guess=torch.full((heat.output_size,), float("nan"), dtype=torch.float64))


@pytest.mark.parametrize("engine", ["petsc", "batched"])
def test_a_state_passed_as_control_and_guess_is_checked_and_solved_as_two(heat, engine):
    """A time step's state is the control u0 and the starting point at once (one tensor for two
    inputs, converted once): the same result as two equal tensors, and a NaN in it is refused
    naming the control, in float32 as in float64."""
    layer = SolveLayer(heat, KSPOptions.preset("jacobi", max_it=4, engine=engine))
    state = control_values(heat, "u0", 16).float()
    kappa = torch.ones(heat.control_size("kappa"), dtype=torch.float32)
    once = layer(u0=state, kappa=kappa, initial_guess=state)
    assert torch.equal(once, layer(u0=state.clone(), kappa=kappa, initial_guess=state.clone()))
    state[3, 5] = state[7, 1] = float("nan")
    with pytest.raises(ValueError, match=r"control 'u0' contains 2 NaN/inf value\(s\)"):
        layer(u0=state, kappa=kappa, initial_guess=state)


def test_adjoint_reuses_the_forward_per_sample_matrices(heat, monkeypatch):
    """A batch of per-sample matrices (kappa) is assembled once, in the forward pass;
    the adjoint copies the kept matrices and gives the same gradient as reassembly."""
    from fempdl.solve.linear_system import LinearSystem
    u0 = control_values(heat, "u0", 3, seed=7)
    kappa = control_values(heat, "kappa", 3, seed=7).requires_grad_()
    calls = []
    original = LinearSystem._assemble_matrix
    monkeypatch.setattr(LinearSystem, "_assemble_matrix", lambda self, *a: (calls.append(1), original(self, *a))[1])
    layer = SolveLayer(heat, KSPOptions(ksp_type="cg", rtol=1e-13, max_it=None))
    out = layer(u0=u0, kappa=kappa)
    grad = torch.autograd.grad(out.square().sum(), kappa)[0]
    assert len(calls) == 3
    with torch.no_grad():                      # no backward follows: nothing is kept
        layer(u0=u0, kappa=kappa.detach() + 0.1)
    assert len(layer.system._kept_matrices._entries) == 1
    monkeypatch.setattr(LinearSystem, "_assemble_matrix", original)
    fresh = SolveLayer(heat, KSPOptions(ksp_type="cg", rtol=1e-13, max_it=None))
    fresh.system._kept_matrices._calls = 0     # keep nothing: the adjoint assembles again
    out = fresh(u0=u0, kappa=kappa)
    assert torch.allclose(torch.autograd.grad(out.square().sum(), kappa)[0], grad, rtol=1e-12, atol=0)


def test_fit_threads():
    from fempdl.core.parallel import fit_threads
    before = torch.get_num_threads()
    try:
        assert fit_threads(1) == 1 and torch.get_num_threads() == 1
        assert fit_threads() == 1          # one rank on this node: torch's current count is kept
        with pytest.raises(ValueError, match="threads"):
            fit_threads(0)
    finally:
        torch.set_num_threads(before)


def test_state_dict_carries_the_cap_and_pickling_says_what_to_do(heat, tmp_path):
    """A model holding a layer saves its K in state_dict (and loads it with weights_only);
    torch.save(model) and deepcopy fail with one message that says how to save instead."""
    import copy

    trained = _ModelWithLayer(heat)
    trained.layer.max_it = 11
    torch.save(trained.state_dict(), tmp_path / "model.pt")
    fresh = _ModelWithLayer(heat)
    fresh.load_state_dict(torch.load(tmp_path / "model.pt", weights_only=True))
    assert fresh.layer.max_it == 11
    for attempt in (lambda: torch.save(trained, tmp_path / "whole.pt"), lambda: copy.deepcopy(trained)):
        with pytest.raises(TypeError, match=r"save model.state_dict\(\) instead"):
            attempt()


class _ModelWithLayer(torch.nn.Module):
    def __init__(self, problem):
        super().__init__()
        self.scale = torch.nn.Parameter(torch.ones(1, dtype=torch.float64))
        self.layer = SolveLayer(problem, KSPOptions(max_it=3))


# ------------------------------------------------------------------ the inverse task's warm start
def _inverse_scene(warm: bool, epochs: int):
    """poisson-inverse for ``epochs`` steps, none cut short by the scene's stop_at."""
    from fempdl.app import scene
    return scene.load("poisson-inverse", [f"solver.warm_start={str(warm).lower()}", f"optimizer.epochs={epochs}",
                                          "optimizer.stop_at=1e-14"])


def test_a_warm_started_inverse_converges_at_a_cap_where_a_cold_one_stalls():
    """At K = 25 Richardson-Jacobi iterations per solve (K_eps = 477), gradient descent on the source
    amplitude from the last step's solution reaches a relative error of ~1e-6 in 300 steps; from zero each
    capped solve has the same large error every step, and the amplitude settles where it cancels it."""
    from fempdl.app.runs import runner
    warm = runner.run(_inverse_scene(True, 300), "fixed", 25, k_eps_value=477)
    cold = runner.run(_inverse_scene(False, 300), "fixed", 25, k_eps_value=477)
    assert warm.total_iterations == cold.total_iterations == 300 * 2 * 25     # forward + adjoint, 25 each
    assert warm.final_metric < 1e-5 and cold.final_metric > 0.1, (warm.final_metric, cold.final_metric)


def test_a_resumed_warm_started_inverse_continues_from_the_saved_solution(tmp_path):
    from fempdl.app.runs import checkpoints, runner
    from fempdl.app.runs.training import CHECKPOINT
    sc = _inverse_scene(True, 40)
    whole = runner.run(sc, "fixed", 25, out_dir=tmp_path / "whole", k_eps_value=477)
    runner.run(sc, "fixed", 25, out_dir=tmp_path / "split", k_eps_value=477, stop_after=15)
    state = checkpoints.load(tmp_path / "split" / CHECKPOINT)
    (saved,) = state["task_state_by_rank"]
    n = saved["coordinates"].shape[0]                       # the mesh's vertices (gmsh versions differ)
    assert n > 300 and saved["coordinates"].shape == (n, 3)
    assert saved["last_solution"].shape[-1] == n and torch.isfinite(saved["last_solution"]).all()
    resumed = runner.run(sc, "fixed", 25, out_dir=tmp_path / "split", k_eps_value=477, resume=True)
    keys = ("epoch", "train_loss", "val_metric", "forward_iterations")
    assert [[row[k] for k in keys] for row in resumed.rows] == [[row[k] for k in keys] for row in whole.rows]


def test_the_inverse_task_state_is_placed_by_coordinates_and_refuses_foreign_entries():
    from fempdl.app.runs import runner
    from fempdl.app.tasks.inverse import InverseTask
    sc = _inverse_scene(True, 1)
    task = InverseTask(sc, runner.solver_options(sc, 5))
    task.train_step(torch.arange(1))
    state = task.state_dict()
    solution = state["last_solution"].clone()
    # Saved by two ranks in another order: each DOF's value is found again by its coordinates.
    n = task.problem.output_size
    order = torch.randperm(n, generator=torch.Generator().manual_seed(0))
    halves = [{"last_solution": solution[..., order[:200]], "coordinates": state["coordinates"][order[:200]]},
              {"last_solution": solution[..., order[200:]], "coordinates": state["coordinates"][order[200:]]}]
    task.last_solution = None
    task.load_state_dict(halves)
    assert torch.equal(task.last_solution, solution)
    with pytest.raises(ValueError, match=r"holds 'last_solution' and 'coordinates', got \['u'\]"):
        task.load_state_dict([{"u": torch.zeros(3)}])
    with pytest.raises(ValueError, match=f"the saved solution has 7 values at {n} points"):
        task.load_state_dict([{"last_solution": torch.zeros(7), "coordinates": state["coordinates"]}])
    with pytest.raises(ValueError, match="does not lie on this mesh"):
        task.load_state_dict([{"last_solution": solution, "coordinates": state["coordinates"] + 0.01}])
    twice = torch.cat([state["coordinates"][:1], state["coordinates"][:-1]])          # one point lost, one doubled
    with pytest.raises(ValueError, match=f"{n} saved points for {n} DOFs"):
        task.load_state_dict([{"last_solution": solution, "coordinates": twice}])
    task.load_state_dict([{}, {}])                                    # an old checkpoint: a cold first step
    assert task.last_solution is None and task.state_dict() == {}
    task.close()


def test_an_inverse_checkpoint_from_before_warm_starts_resumes_cold(tmp_path):
    """A checkpoint written before the inverse task took [solver] warm_start has neither the key in its
    fingerprint nor task state; it ran cold, so a cold run resumes it to the uninterrupted result."""
    from fempdl.app.runs import checkpoints, rundir, runner
    from fempdl.app.runs.training import CHECKPOINT
    sc = _inverse_scene(False, 20)
    whole = runner.run(sc, "fixed", 25, out_dir=tmp_path / "whole", k_eps_value=477)
    runner.run(sc, "fixed", 25, out_dir=tmp_path / "old", k_eps_value=477, stop_after=8)
    state = checkpoints.load(tmp_path / "old" / CHECKPOINT)
    del state["fingerprint"]["run.scene.solver.warm_start"], state["task_state_by_rank"]
    checkpoints.save(tmp_path / "old", state)
    warm = _inverse_scene(True, 20)                       # it is not a warm-started run's checkpoint
    with pytest.raises(rundir.ResumeError, match=r"run.scene.solver.warm_start: '<absent>' -> True"):
        runner.run(warm, "fixed", 25, out_dir=tmp_path / "old", k_eps_value=477, resume=True)
    resumed = runner.run(sc, "fixed", 25, out_dir=tmp_path / "old", k_eps_value=477, resume=True)
    assert [row["val_metric"] for row in resumed.rows] == [row["val_metric"] for row in whole.rows]
