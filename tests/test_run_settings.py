"""RunSettings: one frozen value from the command through the runner to the Trainer, checked when built."""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path

from mpi4py import MPI
import pytest

from fempdl.app import scene
from fempdl.app.runs import runner
from fempdl.app.runs.settings import CHECKPOINT_EVERY, RunSettings
from fempdl.app.runs.training import Trainer


def test_defaults_and_the_derived_values(tmp_path):
    plain = RunSettings()
    assert (plain.out_dir, plain.epochs, plain.seed, plain.parallel, plain.checkpoint_every) \
        == (None, None, None, None, CHECKPOINT_EVERY)
    assert plain.ranks is MPI.COMM_SELF and plain.board_dir is None
    written = RunSettings(out_dir=str(tmp_path), tensorboard=True, parallel="data")
    assert written.out_dir == tmp_path and isinstance(written.out_dir, Path)
    assert written.board_dir == tmp_path / "tensorboard" and written.ranks is MPI.COMM_WORLD
    with pytest.raises(dataclasses.FrozenInstanceError):
        written.epochs = 3


@pytest.mark.parametrize("field, value, message", [
    ("seed", True, r"seed must be an int in \[0, 2\^63 - 1\].*got True"),
    ("seed", -1, r"seed must be an int in \[0, 2\^63 - 1\].*got -1"),
    ("seed", 2 ** 63, r"seed must be an int.*got 9223372036854775808"),
    ("parallel", "threads", r"parallel must be None or one of \['data', 'mesh'\], got 'threads'"),
    ("epochs", 0, "epochs must be a positive int or None, got 0"),
    ("stop_after", 2.5, "stop_after must be a positive int or None, got 2.5"),
    ("checkpoint_every", -1.0, r"checkpoint_every must be a finite number of seconds >= 0, got -1.0"),
    ("checkpoint_every", math.nan, "checkpoint_every must be a finite number of seconds >= 0, got nan"),
    # Accepted before: -1 trained one epoch, nan was ignored, 'soon' failed only after the first epoch.
    ("stop_at_time", -1, "stop_at_time must be a finite number of seconds > 0 or None, got -1"),
    ("stop_at_time", 0.0, "stop_at_time must be a finite number of seconds > 0 or None, got 0.0"),
    ("stop_at_time", math.nan, "stop_at_time must be a finite number of seconds > 0 or None, got nan"),
    ("stop_at_time", "soon", "stop_at_time must be a finite number of seconds > 0 or None, got 'soon'"),
    ("resume", "no", "resume must be True or False, got 'no'"),               # truthy: it resumed
    ("overwrite", 1, "overwrite must be True or False, got 1"),
    ("out_dir", "", r"out_dir must be a directory's path \(str or Path\) or None, got ''; for the working "
                    r"directory give '.'"),                                   # it wrote into the working directory
    ("out_dir", 3, r"out_dir must be a directory's path \(str or Path\) or None, got 3"),
])
def test_bad_values_are_refused_when_built(field, value, message):
    with pytest.raises(ValueError, match=message):
        RunSettings(**{field: value})
    with pytest.raises(ValueError, match=message):          # a replace builds, and checks, anew
        dataclasses.replace(RunSettings(), **{field: value})


def test_resume_and_overwrite_together_are_refused_when_built(tmp_path):
    """The command refused the pair; RunSettings took it, and resumed."""
    message = ("resume=True and overwrite=True contradict each other: resume continues the run in out_dir, "
               "overwrite starts it afresh; give one")
    with pytest.raises(ValueError, match=message):
        RunSettings(out_dir=tmp_path, resume=True, overwrite=True)
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(RunSettings(overwrite=True), resume=True)
    assert RunSettings(out_dir=".").out_dir == Path(".")


def test_outputs_without_a_directory_are_refused_when_a_run_starts():
    """Common settings may lack the out_dir each run adds; a run that starts without it is refused."""
    common = RunSettings(tensorboard=True)
    with pytest.raises(ValueError, match="tensorboard=True writes into out_dir/tensorboard: give out_dir"):
        common.check_outputs()
    with pytest.raises(ValueError, match="resume=True continues the run in out_dir: give out_dir"):
        RunSettings(resume=True).check_outputs()
    with pytest.raises(ValueError, match="tensorboard=True writes into out_dir/tensorboard"):
        Trainer(task=None, batch=1, settings=dataclasses.replace(common, epochs=1))
    with pytest.raises(ValueError, match="the Trainer needs settings.epochs"):
        Trainer(task=None, batch=1, settings=RunSettings())


def test_method_runs_refuse_what_they_cannot_honour(tmp_path):
    sc = scene.load("sip-poisson")
    for change, shown in [({"seed": 3}, "seed=3"), ({"parallel": "data"}, "parallel='data'"),
                          ({"save": True}, "save=True")]:
        with pytest.raises(ValueError, match=f"run_method trains on one process .* got {shown}"):
            runner.run_method(sc, "sip", RunSettings(out_dir=tmp_path / "x"), **change)
    assert not (tmp_path / "x").exists()
