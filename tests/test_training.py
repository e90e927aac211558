"""Training through a capped layer: PRDP end to end, metrics files, and exact resume."""
from __future__ import annotations

import json

import pytest

from fempdl.app import scene
from fempdl.app.runs import runner

from helpers import tiny_scene

TINY = tiny_scene()


@pytest.fixture(scope="module")
def tiny():
    return scene.parse(TINY)


@pytest.fixture(scope="module")
def baseline(tiny):
    return runner.run(tiny, "converged")


def test_prdp_uses_fewer_iterations_than_k_eps_at_a_bounded_error(tiny, baseline):
    prdp = runner.run(tiny, "prdp", k_eps_value=baseline.k_eps)
    assert baseline.k_eps > 4
    assert all(row["k"] == baseline.k_eps for row in baseline.rows)
    # Each epoch passes the 16 training samples once through the layer, forward and backward.
    expected = sum(16 * row["k"] for row in prdp.rows)
    assert prdp.rows[-1]["forward_iterations"] == prdp.rows[-1]["backward_iterations"] == expected
    assert prdp.total_iterations < 0.8 * baseline.total_iterations
    ks = [row["k"] for row in prdp.rows]
    assert ks == sorted(ks) and ks[0] == 1 and ks[-1] > 1 and ks[-1] <= baseline.k_eps
    # Stated bound: within 5x of the converged baseline after 30 short epochs.
    assert prdp.final_metric < 5.0 * baseline.final_metric


def test_resume_after_an_interruption_gives_the_same_metrics(tiny, baseline, tmp_path):
    whole = runner.run(tiny, "prdp", out_dir=tmp_path / "whole", k_eps_value=baseline.k_eps)
    first = runner.run(tiny, "prdp", out_dir=tmp_path / "split", k_eps_value=baseline.k_eps, stop_after=5)
    assert len(first.rows) == 5
    saved = json.loads((tmp_path / "split" / "metrics.json").read_text())
    assert [row["epoch"] for row in saved] == list(range(5))
    resumed = runner.run(tiny, "prdp", out_dir=tmp_path / "split", k_eps_value=baseline.k_eps, resume=True)
    keys = ("epoch", "train_loss", "val_metric", "k", "forward_iterations", "backward_iterations")
    assert [[row[k] for k in keys] for row in resumed.rows] == [[row[k] for k in keys] for row in whole.rows]
    assert (tmp_path / "split" / "metrics.csv").read_text().count("\n") == len(whole.rows) + 1


def test_resume_without_a_checkpoint_is_an_error(tiny, tmp_path):
    with pytest.raises(FileNotFoundError, match="no checkpoint"):
        runner.run(tiny, "fixed", 2, out_dir=tmp_path / "empty", k_eps_value=10, resume=True)


def test_stop_at_ends_training_at_the_target():
    inverse = scene.parse(tiny_scene("inverse", name="tiny-heat", mesh={"h": 0.2},
                                      inverse={"theta_ref": [2.0], "theta_init": [5.0]},
                                      optimizer={"lr": 1.5, "epochs": 500, "stop_at": 1e-6},
                                      prdp={"k0": 1, "dk": 2, "tau_step": 0.95, "delta": 2, "ema_window": 2}))
    run = runner.run(inverse, "converged")
    assert run.final_metric <= 1e-6 < run.rows[-2]["val_metric"]
    assert len(run.rows) < 500


def inverse_scene(**sections) -> scene.Scene:
    return scene.parse(tiny_scene("inverse", **sections))


def test_unrolled_and_implicit_jacobi_train_identically():
    """For Richardson+Jacobi and a source control both diff modes give the exact
    gradient of the capped map: the whole optimisation must coincide."""
    implicit = runner.run(inverse_scene(), "fixed", 6, k_eps_value=50)
    unrolled = runner.run(inverse_scene(solver={"diff": "unrolled"}), "fixed", 6, k_eps_value=50)
    for a, b in zip(implicit.rows, unrolled.rows):
        assert a["val_metric"] == pytest.approx(b["val_metric"], rel=1e-10, abs=1e-14)
        assert a["total_iterations"] == b["total_iterations"]
    assert implicit.rows[-1]["val_metric"] < implicit.rows[0]["val_metric"]


def test_metrics_split_the_wall_time(tiny, baseline):
    """The time parts add up to the wall time, the iterations part is the layers' solve time,
    and the cheap parts are not lost in 'other'."""
    from fempdl.app.runs.training import TIME_FIELDS
    for row in baseline.rows:
        parts = [row[f] for f in TIME_FIELDS]
        assert all(p >= -1e-3 for p in parts)        # differences of clock readings: no real part is negative
        assert sum(parts) == pytest.approx(row["wall_time"], rel=1e-9)
        assert row["time_iterations"] == pytest.approx(row["solve_time"], rel=1e-9)
    last = baseline.rows[-1]
    assert last["time_network"] > 0 and last["time_validation"] > 0 and last["time_assembly"] > 0


def test_files_are_written_on_their_cadence_and_after_the_last_epoch(tiny, tmp_path):
    """With a long checkpoint_every the files are written once, after the call's last epoch (all
    its rows); with 0 after every epoch (the previous checkpoint is then the epoch before)."""
    import torch

    from fempdl.app.runs import checkpoints
    runner.run(tiny, "fixed", 2, out_dir=tmp_path / "rare", k_eps_value=10, stop_after=3, checkpoint_every=1e9)
    state = checkpoints.load(tmp_path / "rare" / checkpoints.CHECKPOINT)
    assert state["epoch"] == 2 and not (tmp_path / "rare" / checkpoints.PREVIOUS).exists()
    assert len(json.loads((tmp_path / "rare" / "metrics.json").read_text())) == 3
    runner.run(tiny, "fixed", 2, out_dir=tmp_path / "each", k_eps_value=10, stop_after=3, checkpoint_every=0.0)
    assert torch.load(tmp_path / "each" / checkpoints.PREVIOUS, weights_only=True)["epoch"] == 1
