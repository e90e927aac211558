"""A scene resolved once (:class:`fempdl.app.runs.plan.ScenePlan`): a command looks its scene's task up
once and checks each run's caps once, before anything is written; its runs train from the plan."""
from __future__ import annotations

import contextlib
import io

import pytest

from fempdl.app import cli, scene
from fempdl.app.runs import plan as plan_module
from fempdl.app.runs import runner
from fempdl.app.runs.plan import ScenePlan

from helpers import CLI_TINY, tiny_scene

TINY = tiny_scene("emulator", CLI_TINY, name="tiny-plan", data={"train": 8, "validation": 2},
                  optimizer={"epochs": 2, "batch": 4})


def counted(monkeypatch, module, name: str) -> list:
    """The arguments of every call of ``module.name`` from now on."""
    calls, original = [], getattr(module, name)

    def wrapper(*args, **kwargs):
        calls.append(args)
        return original(*args, **kwargs)
    monkeypatch.setattr(module, name, wrapper)
    return calls


@pytest.mark.parametrize("argv, caps", [
    (["run"], [("prdp", None), ("converged", None)]),
    (["tradeoff", "--ks", "1,2"], [("fixed", 1), ("fixed", 2), ("prdp", None), ("converged", None)]),
], ids=["run", "tradeoff"])
def test_a_command_looks_its_task_up_once_and_checks_each_cap_once(argv, caps, tmp_path, monkeypatch):
    """`fempdl run` looked the scene's task up 8 times and checked its caps in the command and again in
    every run; the runs now take what the plan checked, before the first was trained."""
    path = tmp_path / "tiny.toml"
    path.write_text(TINY)
    lookups = counted(monkeypatch, plan_module, "spec_of")
    classes = counted(monkeypatch, plan_module, "task_class")
    checks = counted(monkeypatch, plan_module, "check_caps")
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()) as err:
        code = cli.main([argv[0], str(path), *argv[1:], "--out", str(tmp_path / "out"), "--no-progress"])
    assert code == 0, err.getvalue()
    assert len(lookups) == len(classes) == 1
    assert [(mode, k) for _, mode, k, *_ in checks] == caps


def test_the_plan_hands_out_its_checked_caps_and_what_was_measured():
    plan = ScenePlan.of(scene.parse(TINY), caps=[("fixed", 3, "--k"), ("prdp", None)])
    assert (plan.spec.name, plan.parallel, plan.trains_methods, plan.k_eps) == ("emulator", None, False, None)
    fixed = plan.caps("fixed", 3)
    assert fixed is plan.planned[0] and (fixed.mode, fixed.k, fixed.options.max_it) == ("fixed", 3, 3)
    measured = plan.measured(12)
    assert measured.caps("prdp") is plan.caps("prdp") and measured.k_eps == 12
    assert plan.caps("fixed", 5).options.max_it == 5 and len(plan.planned) == 2     # checked when asked for
    with pytest.raises(ValueError, match=r"--k 99999999999 cannot cap the solver of scene 'tiny-plan'"):
        plan.with_caps(("fixed", 99999999999, "--k"))
    with pytest.raises(ValueError, match="give k exactly when mode='fixed'"):
        plan.caps("fixed")
    with pytest.raises(ValueError, match=r"mode must be one of \['fixed', 'converged', 'prdp'\], got 'slow'"):
        plan.caps("slow")


def test_a_plan_refuses_a_parallel_mode_and_settings_that_disagree_with_it():
    sc = scene.parse(TINY)
    with pytest.raises(ValueError, match=r"parallel must be None, 'data' or 'mesh', got 'threads'"):
        ScenePlan.of(sc, parallel="threads")
    with pytest.raises(ValueError, match="--parallel mesh distributes the mesh"):
        ScenePlan.of(sc, parallel="mesh")
    plan = ScenePlan.of(sc)
    assert plan.in_parallel("data").parallel == "data" and plan.parallel is None
    with pytest.raises(ValueError, match=r"settings.parallel='data' but the plan trains with parallel=None"):
        runner.train(plan, plan.caps("fixed", 2), parallel="data")
