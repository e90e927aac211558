"""Scenes on Newton layers: the nonlinear-heat emulator under PRDP (what K caps by [solver] refine, K_eps,
exact Newton counts, the trade-off sweep) and the nonlinear-poisson SIP and HIG scenes (the exact inverse
without a PDE solve, the per-step Jacobian of HIG, both training)."""
from __future__ import annotations

import logging
import re

from mpi4py import MPI
import dolfinx.fem
import pytest
import torch
import ufl

from fempdl import KSPOptions, NewtonOptions, NonlinearProblem, NonlinearSolveLayer, SolveLayer, forms, mesh
from fempdl.app import scene
from fempdl.app.reports import tradeoff
from fempdl.app.runs import runner
from fempdl.app.runs.timesplit import TIME_PARTS
from fempdl.app.tasks.learned_inverse import InversionTask
from fempdl.app.tasks.nonlinear_emulator import NonlinearEmulatorTask
from fempdl.methods.hig import HIG
from fempdl.methods.k_eps import converged_caps, newton_k_eps
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.methods.sip_nonlinear import ExactNonlinearInverse

from helpers import tiny_scene

TRAIN = 8
# The tiny emulator on one backward-Euler step of nonlinear heat (63 DOFs), Newton from the state.
NONLINEAR_HEAT = {
    "scene": {"name": "tiny-nonlinear-heat"},
    "mesh": {"h": 0.3},
    "pde": {"type": "nonlinear-heat", "dt": 0.01, "alpha": 20.0},
    "data": {"train": TRAIN, "validation": 4},
    "optimizer": {"epochs": 6, "batch": 4},
    "solver": {"preset": "lu", "warm_start": True},
    # Refine at every decision (every epoch from the third): any ratio is a plateau, any change a refinement.
    "prdp": {"k0": 1, "dk": 1, "tau_step": 0.01, "tau_stop": 1.0, "delta": 2, "ema_window": 1},
}
# Per rule: the inner preset and the extra [solver] keys.
RULES = {
    "newton": {"preset": "lu"},
    "inner": {"preset": "jacobi", "refine": "inner"},
    "both": {"preset": "gmres", "refine": "both", "inner_per_k": 2},
}


def emulator_scene(refine: str = "newton", **sections) -> scene.Scene:
    return scene.parse(tiny_scene("emulator", NONLINEAR_HEAT, {"solver": RULES[refine]}, sections))


def per_epoch(rows: list, key: str) -> list:
    values = [row[key] for row in rows]
    return [b - a for a, b in zip([0] + values, values)]


# ------------------------------------------------------------------ bundled scenes and the schema
def test_the_bundled_nonlinear_scenes_parse():
    emulator = scene.load("nonlinear-heat-emulator")
    assert (emulator.task, emulator.pde.type, emulator.solver.refine, emulator.solver.preset) \
        == ("emulator", "nonlinear-heat", "newton", "lu")
    assert emulator.pde.alpha > 0 and emulator.pde.theta is None and emulator.solver.warm_start
    assert "lag_preconditioner" not in emulator.as_dict()["solver"]
    for name, task in (("sip-nonlinear", "sip"), ("hig-nonlinear", "hig")):
        sc = scene.load(name)
        assert (sc.task, sc.pde.type) == (task, "nonlinear-poisson") and sc.pde.dt is None
        assert sc.pde.alpha > 0
    assert scene.load("sip-nonlinear").sip.inverse == "exact"
    # A linear PDE neither takes nor shows the Newton keys.
    heat = scene.load("heat-emulator-2d")
    assert heat.pde.alpha is None and heat.solver.refine is None
    assert "alpha" not in heat.as_dict()["pde"] and "refine" not in heat.as_dict()["solver"]


@pytest.mark.parametrize("edit, fragment", [
    ({"solver": {"preset": "lu", "refine": "inner"}}, "refine = 'inner' caps the inner Krylov iterations"),
    ({"solver": {"preset": "jacobi", "inner_per_k": 3}}, "inner_per_k applies to refine = 'both'"),
    ({"solver": {"preset": "cg"}}, "the Jacobian of kappa (1 + alpha u^2) grad u is not symmetric"),
    ({"solver": {"preset": "jacobi", "refine": "inner", "diff": "unrolled"}}, "it needs refine = 'newton'"),
    ({"solver": {"lag_preconditioner": True}}, "[solver] lag_preconditioner do(es) not apply to pde"),
    ({"pde": {"theta": 0.5}}, "[pde] theta do(es) not apply to pde 'nonlinear-heat'"),
    ({"pde": {"type": "heat", "alpha": 2.0}}, "[pde] alpha do(es) not apply to pde 'heat'"),
    ({"pde": {"type": "heat", "alpha": None}, "solver": {"preset": "jacobi", "refine": "inner"}},
     "[solver] refine do(es) not apply to pde 'heat'"),
    ({"pde": {"type": "heat", "alpha": None}, "solver": {"preset": "lu"}}, "preset 'lu' has no iteration cap"),
    ({"solver": {"refine": "twice"}}, "[solver] refine must be one of ['newton', 'inner', 'both']"),
])
def test_newton_solver_keys_are_checked(edit, fragment):
    with pytest.raises(scene.SceneError) as info:
        scene.parse(tiny_scene("emulator", NONLINEAR_HEAT, edit), source="bad.toml")
    assert fragment in str(info.value), str(info.value)


def test_the_iterative_presets_a_refusal_names_are_the_accepted_ones():
    with pytest.raises(scene.SceneError) as info:
        scene.parse(tiny_scene("emulator", NONLINEAR_HEAT, {"solver": {"preset": "lu", "refine": "inner"}}))
    named = re.search(r"choose an iterative preset \(([^)]*)\)", str(info.value)).group(1).split(", ")
    assert named == ["jacobi", "gmres", "gmres-ilu"]                   # not cg: the Jacobian is not symmetric
    for preset in named:
        edit = {"solver": {"preset": preset, "refine": "inner"}}
        assert scene.parse(tiny_scene("emulator", NONLINEAR_HEAT, edit)).solver.preset == preset


def test_the_nonlinear_sip_scene_takes_the_exact_inverse_only():
    with pytest.raises(scene.SceneError, match="inverse must be 'exact' for nonlinear-poisson"):
        scene.parse(tiny_scene("sip", pde={"type": "nonlinear-poisson"}, sip={"inverse": "tikhonov", "damping": 0.1}))


# ------------------------------------------------------------------ the emulator: what K caps, K_eps, counts
def test_k_eps_is_newton_k_eps_under_the_scenes_rule():
    sc = emulator_scene("both")
    task = runner.build_task(sc, runner.layer_options(sc, 1))
    try:
        assert isinstance(task, NonlinearEmulatorTask) and isinstance(task.caps, NewtonCaps)
        assert (task.caps.refine, task.caps.inner_per_k) == ("both", 2)
        inputs = task.k_eps_rhs()
        assert torch.equal(inputs["initial_guess"], inputs["u0"])          # warm start: Newton from the state
        expected = newton_k_eps(task.caps, rtol=sc.data.k_eps_rtol, **inputs)
        need = converged_caps(task.layer, rtol=sc.data.k_eps_rtol, **inputs)
        assert task.caps.converged == need and expected == max(need.newton_steps, -(-need.inner_iterations // 2))
        task.caps.converged = None
        assert runner.measure_k_eps(task, sc) == expected >= 2
        assert task.caps.converged == need
        steps = newton_k_eps(NewtonCaps(task.layers, "newton"), rtol=sc.data.k_eps_rtol, **inputs)
        assert steps == need.newton_steps
    finally:
        task.close()
    result = runner.run(sc, "converged", epochs=1)
    assert result.k_eps == expected and result.rows[0]["k"] == expected and result.converged_caps == need


@pytest.mark.parametrize("k", [1, 2])
def test_a_fixed_k_runs_exactly_k_newton_steps_per_sample(k):
    sc = emulator_scene("newton")
    rows = runner.run(sc, "fixed", k, epochs=2).rows
    # Forward: K steps of one LU solve each per sample; backward: one adjoint LU solve per sample.
    assert per_epoch(rows, "newton_steps") == [k * TRAIN] * 2
    assert per_epoch(rows, "forward_iterations") == [k * TRAIN] * 2
    assert per_epoch(rows, "backward_iterations") == [TRAIN] * 2
    assert all(row["k"] == k for row in rows)


@pytest.mark.parametrize("refine", ["newton", "inner", "both"])
def test_prdp_refines_k_and_moves_the_caps_by_the_rule(refine):
    sc = emulator_scene(refine)
    result = runner.run(sc, "prdp")
    ks = [row["k"] for row in result.rows]
    assert ks[0] == 1 and ks[-1] > 1 and ks == sorted(ks) and ks[-1] <= result.k_eps
    steps, inner = per_epoch(result.rows, "newton_steps"), per_epoch(result.rows, "forward_iterations")
    need = result.converged_caps
    for k, s, its in zip(ks, steps, inner):
        if refine == "newton":
            assert (s, its) == (k * TRAIN, k * TRAIN)                  # LU: one "iteration" per step
        elif refine == "inner":     # Newton takes the steps converged solves need; K Jacobi iterations each
            assert (s, its) == (need.newton_steps * TRAIN, k * need.newton_steps * TRAIN)
        else:                       # K steps of inner_per_k K iterations, neither past what converged solves need
            n, per_step = min(k, need.newton_steps), min(2 * k, need.inner_iterations)
            assert (s, its) == (n * TRAIN, n * per_step * TRAIN)


def test_under_both_neither_cap_runs_past_what_converged_solves_need():
    # Jacobi with inner_per_k = 1: K_eps is the inner iterations a step needs, well above the Newton steps.
    sc = emulator_scene("both", solver={"preset": "jacobi", "inner_per_k": 1}, optimizer={"epochs": 6},
                        prdp={"k0": 2})
    base = runner.run(sc, "converged", epochs=1)
    need = base.converged_caps
    assert (need.newton_steps, need.inner_iterations, base.k_eps) == (3, 15, 15)
    # The baseline runs the Newton steps converged solves need, not K_eps of them.
    assert (base.rows[0]["newton_steps"], base.rows[0]["forward_iterations"]) == (3 * TRAIN, 3 * 15 * TRAIN)
    prdp = runner.run(sc, "prdp", k_eps_value=base.k_eps, converged_caps=need)
    ks = [row["k"] for row in prdp.rows]
    assert ks[0] == 2 and max(ks) > 3
    for k, s, its in zip(ks, per_epoch(prdp.rows, "newton_steps"), per_epoch(prdp.rows, "forward_iterations")):
        assert (s, its) == (min(k, 3) * TRAIN, min(k, 3) * min(k, 15) * TRAIN)


def test_the_caps_follow_the_rule_on_the_layer():
    sc = emulator_scene("both")
    task = runner.build_task(sc, runner.layer_options(sc, 1))
    try:
        task.caps.max_it = 3
        assert (task.layer.max_it, task.layer.inner_max_it) == (3, 6)
        assert task.reference.max_it is None            # the reference stays converged
    finally:
        task.close()


@pytest.mark.parametrize("refine", ["inner", "both"])
def test_newton_caps_refuse_to_cap_the_inner_solve_of_an_unrolled_layer(refine):
    problem = forms.nonlinear_diffusion.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.5), ("f",), alpha=2.0)
    inner = KSPOptions.preset("gmres", max_it=None, rtol=1e-10)         # converged: what unrolling needs
    layer = NonlinearSolveLayer(problem, NewtonOptions(max_it=2, ksp=inner), diff="unrolled")
    try:
        with pytest.raises(ValueError) as by_layer:
            layer.inner_max_it = 1
        with pytest.raises(ValueError) as by_caps:           # at construction, not when PRDP first sets K
            NewtonCaps(layer, refine)
        assert str(by_caps.value) == str(by_layer.value)
        assert "diff='unrolled' needs the exact Newton step" in str(by_caps.value)
        assert NewtonCaps(layer, "newton").refine == "newton"
    finally:
        layer.close()


def test_a_resumed_prdp_run_continues_with_its_caps(tmp_path):
    sc = emulator_scene("inner", optimizer={"epochs": 5})
    whole = runner.run(sc, "prdp").rows
    runner.run(sc, "prdp", out_dir=tmp_path, stop_after=3)
    resumed = runner.run(sc, "prdp", out_dir=tmp_path, resume=True).rows
    for key in ("k", "val_metric", "newton_steps", "forward_iterations", "backward_iterations"):
        assert [row[key] for row in resumed] == pytest.approx([row[key] for row in whole], rel=1e-9), key
    assert (tmp_path / "metrics.csv").read_text().splitlines()[0].endswith(",newton_steps,backward_newton_steps")


def test_the_unrolled_backward_newton_steps_are_counted_apart(tmp_path):
    sc = emulator_scene("newton", solver={"diff": "unrolled"})
    rows = runner.run(sc, "fixed", 2, epochs=2, out_dir=tmp_path / "unrolled").rows
    backward = per_epoch(rows, "backward_newton_steps")
    forward = [total - steps for total, steps in zip(per_epoch(rows, "newton_steps"), backward)]
    assert forward == backward == [2 * TRAIN] * 2          # the unrolled pass runs the forward's steps back
    header = (tmp_path / "unrolled" / "metrics.csv").read_text().splitlines()[0].split(",")
    assert header[-2:] == ["newton_steps", "backward_newton_steps"]
    implicit = runner.run(emulator_scene("newton"), "fixed", 2, epochs=1).rows
    assert (implicit[0]["newton_steps"], implicit[0]["backward_newton_steps"]) == (2 * TRAIN, 0)


def test_a_checkpoint_from_before_the_backward_newton_steps_resumes(tmp_path):
    from fempdl.app.runs import checkpoints
    from fempdl.app.runs.training import CHECKPOINT
    sc = emulator_scene("newton", solver={"diff": "unrolled"})
    runner.run(sc, "fixed", 1, epochs=2, out_dir=tmp_path, stop_after=1)
    state = checkpoints.load(tmp_path / CHECKPOINT)
    for row in state["rows"]:
        del row["backward_newton_steps"]
    checkpoints.save(tmp_path, state)
    rows = runner.run(sc, "fixed", 1, epochs=2, out_dir=tmp_path, resume=True).rows
    assert "backward_newton_steps" not in rows[0] and rows[1]["backward_newton_steps"] == 2 * TRAIN
    lines = (tmp_path / "metrics.csv").read_text().splitlines()
    assert lines[0].endswith(",newton_steps,backward_newton_steps")
    assert lines[1].endswith(f",{2 * TRAIN},") and lines[2].endswith(f",{4 * TRAIN},{2 * TRAIN}")


def test_the_tradeoff_sweep_runs_and_counts_newton_steps(tmp_path):
    sc = emulator_scene("newton", optimizer={"epochs": 4})
    runs = tradeoff.sweep(sc, ks=[1], out_dir=tmp_path)
    assert list(runs) == ["K=1", f"K_eps={runs['PRDP'].k_eps}", "PRDP"]
    assert runs["K=1"].newton_steps == 4 * TRAIN
    split = tradeoff.savings(runs)
    baseline = runs[f"K_eps={runs['PRDP'].k_eps}"]
    assert split["newton_savings"] == pytest.approx(1 - runs["PRDP"].newton_steps / baseline.newton_steps)
    assert "newton steps" in tradeoff.comparison_table(runs)
    assert any(line.startswith("Newton steps:") for line in tradeoff.summary_lines(split))
    tradeoff.write_report(sc, runs, split, tmp_path)
    assert (tmp_path / "tradeoff.csv").read_text().splitlines()[0].endswith(",newton_steps")


def test_the_converged_caps_are_measured_once_and_logged_with_k_eps(caplog):
    sc = emulator_scene("inner", optimizer={"epochs": 1})
    with caplog.at_level(logging.INFO, logger="fempdl.app.runs.runner"):
        runs = tradeoff.sweep(sc, ks=[1, 2])
    need = runs["PRDP"].converged_caps
    # One measurement, by the baseline: the fixed-K and PRDP runs take it; its Newton steps are no K_eps.
    assert [r.getMessage() for r in caplog.records if r.name == "fempdl.app.runs.runner"] == [
        f"K_eps = {need.inner_iterations} (Newton, refine=inner, to rtol {sc.data.k_eps_rtol}; what converged "
        f"solves take at most: Newton steps {need.newton_steps}, inner iterations per step {need.inner_iterations})"]
    assert all(run.converged_caps == need for run in runs.values())
    assert [run.newton_steps for run in runs.values()] == [need.newton_steps * TRAIN] * 4


def made_up_run(mode: str, k: int, wall: float, steps: int, **seconds: float) -> runner.RunResult:
    """A one-epoch run of ``steps`` Newton steps (one LU iteration each) taking ``seconds`` per part."""
    row = {"epoch": 0, "k": k, "val_metric": 1.0, "total_iterations": steps, "newton_steps": steps,
           "wall_time": wall, **{f"time_{part}": seconds.get(part, 0.0) for part in TIME_PARTS}}
    return runner.RunResult(scene="made-up", mode=mode, k_eps=4, rows=[row], out_dir=None)


def test_the_clock_bound_counts_what_the_cap_moves():
    # Each Newton step assembles J and F and sets up its solve: with the Newton cap, those shrink too.
    base = made_up_run("converged", 4, 10.0, 400, iterations=2.0, setup=0.5, assembly=3.0, network=2.0,
                       validation=2.0, other=0.5)
    prdp = made_up_run("prdp", 1, 5.5, 100, iterations=0.5, setup=0.125, assembly=0.75, network=2.0,
                       validation=2.0, other=0.125)
    runs = {"K_eps=4": base, "PRDP": prdp}
    newton = tradeoff.savings(runs, refine="newton")
    assert newton["max_wall_time_savings"] == pytest.approx(0.55)              # (2 + 0.5 + 3) / 10
    assert newton["wall_time_savings"] == pytest.approx(0.45) and newton["newton_savings"] == 0.75
    assert newton["predicted_wall_time_savings"] == pytest.approx(0.55 * 0.75)
    assert ("the clock: the solver's iterations and the Newton steps' assembly and set-up are 55% of the "
            "baseline's time, so PRDP can save at most 55% of the wall time here; its savings predict 41%, it "
            "reached 45%") == tradeoff.summary_lines(newton)[3]
    # refine = "inner" leaves the Newton steps as converged solves need: the iterations alone shrink, and a
    # saving past their share is said to come from elsewhere.
    inner = tradeoff.savings(runs, refine="inner")
    assert (inner["max_wall_time_savings"], inner["capped_parts"]) == (pytest.approx(0.2), ["iterations"])
    line = tradeoff.summary_lines(inner)[3]
    assert line.startswith("the clock: the solver's iterations are 20% of the baseline's time, so PRDP can save "
                           "at most 20% of the wall time here; its iteration saving predicts 15%, it reached 45% "
                           "(past the bound: costs the cap does not move differ between the runs")
    assert "past the bound" not in tradeoff.summary_lines(newton)[3]


# ------------------------------------------------------------------ SIP and HIG on nonlinear-poisson
@pytest.fixture(scope="module")
def nonlinear_poisson():
    msh = mesh.load("lshape", MPI.COMM_WORLD, h=0.3)
    problem = forms.nonlinear_diffusion.problem(msh, ("f",), kappa=0.05, alpha=2.0)
    layer = NonlinearSolveLayer(problem, NewtonOptions(ksp="lu", rtol=1e-13, atol=1e-14))
    yield problem, layer
    layer.close()


def test_the_nonlinear_sip_inverse_is_exact(nonlinear_poisson):
    problem, layer = nonlinear_poisson
    gen = torch.Generator().manual_seed(0)
    f = 3.0 * torch.randn(3, problem.control_size("f"), generator=gen, dtype=torch.float64)   # boundary values too
    with torch.no_grad():
        y = layer(f=f)
    assert y.abs().max() > 0.3            # kappa (1 + alpha u^2) far from constant
    inverse = ExactNonlinearInverse(layer, "f")
    free = inverse.free
    x0 = torch.zeros_like(f)
    x0[:, problem.bc_dofs] = f[:, problem.bc_dofs]                 # P^-1 keeps x0's boundary values
    x_star = inverse(x0, y)
    assert ((x_star - f)[:, free].abs().max() / f.abs().max()).item() < 1e-10
    # With other boundary values the inverse still reproduces y (those values are x0's).
    x_other = inverse(torch.zeros_like(f), y)
    with torch.no_grad():
        assert ((layer(f=x_other) - y).abs().max() / y.abs().max()).item() < 1e-10
    # eta interpolates between x0 and P^-1(y*).
    half = ExactNonlinearInverse(layer, "f", eta=0.5)(x0, y)
    assert torch.allclose(half, 0.5 * (x0 + x_star), atol=1e-12)


def test_the_nonlinear_sip_inverse_refuses_a_linear_problem_and_a_nonaffine_control(nonlinear_poisson):
    problem, layer = nonlinear_poisson
    with pytest.raises(TypeError, match="NonlinearProblem"):
        ExactNonlinearInverse(SolveLayer(forms.poisson.problem(problem.V.mesh)), "f")
    both = forms.nonlinear_diffusion.problem(problem.V.mesh, ("f", "alpha"))
    with pytest.raises(ValueError, match="control on the solution space; 'alpha' is not"):
        ExactNonlinearInverse(NonlinearSolveLayer(both, NewtonOptions(ksp="lu")), "alpha")
    # -div grad u = f^2: the source enters squared, so no mass matrix maps it to the residual.
    V = problem.V
    u, f, v = dolfinx.fem.Function(V), dolfinx.fem.Function(V), ufl.TestFunction(V)
    squared = NonlinearProblem(ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - f ** 2 * v * ufl.dx, u, problem.bcs,
                               controls={"f": f})
    with pytest.raises(ValueError, match="needs a residual affine in 'f'"):
        ExactNonlinearInverse(NonlinearSolveLayer(squared, NewtonOptions(ksp="lu")), "f")


def test_hig_by_jacrev_is_the_state_dependent_jacobian_of_the_newton_solve(nonlinear_poisson):
    problem, layer = nonlinear_poisson
    gen = torch.Generator().manual_seed(1)
    x = 3.0 * torch.randn(2, problem.control_size("f"), generator=gen, dtype=torch.float64)

    def physics(f):
        return layer(f=f)
    by_rows = HIG._physics_jacobian(physics, x, problem.output_size)
    by_jacrev = HIG._physics_jacrev(physics, x, problem.output_size)
    assert torch.allclose(by_rows, by_jacrev, rtol=1e-9, atol=1e-12)
    # It depends on the state: twice the source is not twice the solution's Jacobian.
    assert not torch.allclose(HIG._physics_jacrev(physics, 2 * x, problem.output_size), by_jacrev, rtol=1e-3)
    with pytest.raises(ValueError, match="physics_jacobian must be"):
        HIG(torch.nn.Linear(2, 2)).jacobian(torch.zeros(1, 2), physics_jacobian="columns")


def test_the_data_and_the_validation_are_not_counted_as_training():
    sc = scene.parse(tiny_scene("sip", pde={"type": "nonlinear-poisson", "kappa": 0.05, "alpha": 2.0},
                                optimizer={"epochs": 2}))
    train = sc.data.train
    # SIP's exact nonlinear inverse solves no PDE: nothing to count, from the first epoch on.
    rows = runner.run_method(sc, "sip").rows
    assert [(r["newton_steps"], r["forward_iterations"], r["total_iterations"]) for r in rows] == [(0, 0, 0)] * 2
    # Backprop: one Newton solve and one adjoint LU solve per training sample per epoch, no more.
    instance = InversionTask(sc, "backprop")
    try:
        assert (instance.layer.stats.newton_solves, instance.layer.stats.forward_iterations) == (0, 0)
        assert instance.reference.stats.newton_solves == train + sc.data.validation
        instance.train_step(torch.arange(train))
        instance.validate()
        assert (instance.layer.stats.newton_solves, instance.layer.stats.backward_iterations) == (train, train)
    finally:
        instance.close()
    rows = runner.run_method(sc, "backprop").rows
    assert per_epoch(rows, "backward_iterations") == [train] * 2
    assert per_epoch(rows, "forward_iterations") == per_epoch(rows, "newton_steps")     # LU: one per step
    # HIG's validation solves P(x0) too, on the reference layer.
    hig = InversionTask(scene.parse(tiny_scene("hig", pde={"type": "nonlinear-poisson", "alpha": 2.0})), "hig")
    try:
        hig.validate()
        assert hig.layer.stats.newton_solves == 0
        assert hig.reference.stats.newton_solves == hig.train_size + 2 * hig.val_size
    finally:
        hig.close()


def test_the_linear_sip_rows_count_the_inverse_solves_only():
    sc = scene.parse(tiny_scene("sip", optimizer={"epochs": 3}))
    rows = runner.run_method(sc, "sip").rows
    # The exact linear inverse evaluates P(x0): one LU solve per training sample, every epoch the same.
    assert per_epoch(rows, "forward_iterations") == [sc.data.train] * 3
    assert [r["backward_iterations"] for r in rows] == [0] * 3


@pytest.mark.parametrize("task", ["sip", "hig"])
def test_sip_and_hig_train_on_the_nonlinear_inverse(task):
    sc = scene.parse(tiny_scene(task, pde={"type": "nonlinear-poisson", "kappa": 0.05, "alpha": 2.0},
                                optimizer={"epochs": 8}))
    assert sc.pde.type == "nonlinear-poisson"
    rows = runner.run_method(sc, task).rows
    assert rows[-1]["val_metric"] < 0.9 * rows[0]["val_metric"], [r["val_metric"] for r in rows]
    baseline = runner.run_method(sc, "backprop", epochs=2).rows         # Adam through the Newton solve
    assert len(baseline) == 2 and all(0 < r["val_metric"] < 10 for r in baseline)
    instance = InversionTask(sc, task)
    try:
        assert isinstance(instance.layer, NonlinearSolveLayer) and instance.nonlinear
        assert instance.x_train[:, instance.problem.bc_dofs].abs().max() == 0
    finally:
        instance.close()
