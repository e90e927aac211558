"""The command reports what is wrong with its inputs in one line and exit code 2, never a traceback."""
from __future__ import annotations

import pytest

from fempdl.app import cli
from helpers import tiny_scene


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(tiny_scene(name="tiny", optimizer={"epochs": 2}))
    return path


def one_line_error(argv, capsys) -> str:
    code = cli.main([str(a) for a in argv])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    # Log lines of the run may come first (stderr is no terminal here); the error is the last line.
    assert "Traceback" not in err and all(line.startswith("fempdl: ") for line in lines), err
    return lines[-1]


@pytest.mark.parametrize("args, fragment", [
    (["--set", "mesh.name=no/such/mesh.msh"], "no/such/mesh.msh"),
    (["--set", "mesh.h=40.0"], "h"),
    (["--k", "3000000000"], "max_it must be <="),
    (["--set", "optimizer.lr=1e30", "--k", "2"], "NaN"),
], ids=["missing-mesh", "h-beyond-geometry", "k-beyond-petsc-int", "diverging-lr"])
def test_bad_inputs_give_one_line_and_exit_2(scene_file, tmp_path, capsys, args, fragment):
    line = one_line_error(["run", scene_file, "--out", tmp_path / "out", "--no-progress", "--no-baseline", *args],
                          capsys)
    assert fragment in line, line


def test_a_garbage_mesh_file_gives_one_line(scene_file, tmp_path, capsys):
    garbage = tmp_path / "garbage.msh"
    garbage.write_text("this is no gmsh file\n")
    line = one_line_error(["run", scene_file, "--out", tmp_path / "out", "--no-progress", "--no-baseline",
                           "--k", "2", "--set", f"mesh.name={garbage}"], capsys)
    assert "garbage.msh" in line, line


def test_a_seed_beyond_the_generators_range_is_an_argument_error(scene_file, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(["run", str(scene_file), "--seed", str(2 ** 64)])
    assert info.value.code == 2 and "must be in [0, 2^63 - 1]" in capsys.readouterr().err


def test_resume_with_fewer_epochs_than_done_is_refused(scene_file, tmp_path, capsys):
    """It used to report the old result as if it had run."""
    out = tmp_path / "out"
    base = ["run", scene_file, "--out", out, "--no-progress", "--no-baseline", "--k", "2"]
    assert cli.main([str(a) for a in base + ["--epochs", "3"]]) == 0
    capsys.readouterr()
    line = one_line_error(base + ["--resume", "--epochs", "2"], capsys)
    assert "already holds 3 epochs, more than the 2 asked for" in line, line
