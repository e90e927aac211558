"""A run's files through the Python API: an earlier run is never replaced unasked, and every value
read back from a checkpoint is checked before it is used."""
from __future__ import annotations

import pytest
import torch

from fempdl.app import scene
from fempdl.app.runs import checkpoints, rundir, runner

from helpers import tiny_scene


@pytest.fixture(scope="module")
def inverse():
    return scene.parse(tiny_scene("inverse", optimizer={"epochs": 3}))


def train(inverse, out, **kw):
    return runner.run(inverse, "fixed", 2, out_dir=out, k_eps_value=20, **kw)


def test_a_finished_run_is_not_replaced_without_overwrite(inverse, tmp_path):
    """runner.run(..., out_dir=D) on a finished run used to replace it (176 metric rows became 4)."""
    first = train(inverse, tmp_path)
    with pytest.raises(rundir.RunDirectoryError, match="holds the files of an earlier run; pass resume=True"):
        train(inverse, tmp_path)
    assert checkpoints.load(tmp_path / checkpoints.CHECKPOINT)["rows"] == first.rows      # untouched
    assert len(train(inverse, tmp_path, resume=True).rows) == 3
    assert len(train(inverse, tmp_path, overwrite=True).rows) == 3


@pytest.mark.parametrize("edit, fragment", [
    ({"epoch": -5}, "epoch -5 is not a whole number >= 0"),
    ({"epoch": 7}, "metric rows for 8 epochs"),
    ({"epoch": 1.5}, "epoch 1.5 is not a whole number"),
    ({"elapsed": float("nan")}, "is not a time in seconds"),
    ({"k": 0}, "k 0 is not an iteration cap"),
    ({"layer_stats_by_rank": []}, "one list per rank"),
    ({"model": [1, 2]}, "model is a list, not a dict"),
], ids=["negative-epoch", "epoch-beyond-rows", "fractional-epoch", "nan-time", "zero-k", "no-ranks", "model-list"])
def test_a_malformed_checkpoint_is_refused_naming_what(inverse, tmp_path, edit, fragment):
    train(inverse, tmp_path)
    path = tmp_path / checkpoints.CHECKPOINT
    state = torch.load(path, weights_only=True)
    state.update(edit)
    torch.save(state, path)
    with pytest.raises(checkpoints.CheckpointError, match=fr"is malformed \(.*{fragment}"):
        train(inverse, tmp_path, resume=True)


def test_a_checkpoint_whose_tensors_do_not_fit_is_refused(inverse, tmp_path):
    train(inverse, tmp_path)
    path = tmp_path / checkpoints.CHECKPOINT
    state = torch.load(path, weights_only=True)
    state["model"] = {name: torch.zeros(7) for name in state["model"]}
    torch.save(state, path)
    with pytest.raises(checkpoints.CheckpointError, match="model or optimizer state does not fit this run's"):
        train(inverse, tmp_path, resume=True)


def test_a_resume_refuses_a_mesh_file_that_changed_at_the_same_path(tmp_path):
    """The fingerprint holds the mesh file's SHA-256: a new file at the old path trained silently before."""
    import shutil

    from fempdl.core.resources import bundled_meshes

    path = tmp_path / "domain.msh"
    shutil.copyfile(bundled_meshes() / "lshape.msh", path)
    sc = scene.parse(tiny_scene("inverse", mesh={"name": str(path), "h": None}, optimizer={"epochs": 2}))
    out = tmp_path / "run"
    train(sc, out)
    text = path.read_text()
    path.write_text(text.replace("$Nodes", "$Nodes\n", 1))          # the same mesh, another file content
    with pytest.raises(rundir.ResumeError, match=r"run.mesh_sha256: '[0-9a-f]{64}' -> '[0-9a-f]{64}'"):
        train(sc, out, resume=True)
