"""Nothing silently wrong in the command and the runner: output directories holding your files,
damaged checkpoints, PETSc options rejected only at set-up, and thread counts, caps and seeds out of
range all end in one clear error (exit 2 from the command) before anything is replaced or trained."""
from __future__ import annotations

import argparse
import shutil

import pytest
import torch

from fempdl.app import cli, scene
from fempdl.app.runs import checkpoints, files, rundir, runner

from helpers import finished_run, one_line_error, tiny_scene

SCENE = tiny_scene("inverse", name="hostile-app", optimizer={"epochs": 2})


@pytest.fixture
def scene_file(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    return path


def run_argv(scene_file, out, *extra):
    return ["run", scene_file, "--k", 4, "--out", out, "--no-progress", "--no-baseline", *extra]


# ------------------------------------------------------------------ output directories
def test_the_command_refuses_a_directory_of_your_files_and_overwrite_keeps_what_it_does_not_write(
        scene_file, tmp_path, capsys):
    """A directory holding only your time_split.png was accepted and the file replaced."""
    out = tmp_path / "mine"
    out.mkdir()
    (out / "time_split.png").write_bytes(b"my plot")
    (out / "notes.txt").write_text("my notes")
    line = one_line_error(run_argv(scene_file, out), capsys)
    assert f"{str(out)!r} holds no fempdl run but files fempdl did not write (notes.txt, time_split.png)" in line, line
    assert "choose another --out, or pass --overwrite" in line, line
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt", "time_split.png"]     # nothing written
    assert (out / "time_split.png").read_bytes() == b"my plot"
    assert cli.main([str(a) for a in run_argv(scene_file, out, "--overwrite")]) == 0
    assert (out / "notes.txt").read_text() == "my notes"                 # what fempdl does not write stays
    assert (out / "k4" / checkpoints.CHECKPOINT).exists()


def test_runner_run_refuses_a_directory_of_your_files_unless_overwrite(tmp_path):
    sc = scene.parse(SCENE)
    (tmp_path / "results.csv").write_text("mine")
    with pytest.raises(rundir.RunDirectoryError, match=r"holds no fempdl run but files fempdl did not write "
                                                       r"\(results.csv\); .*choose another out_dir, or pass "
                                                       r"overwrite=True"):
        runner.run(sc, "fixed", 4, out_dir=tmp_path, k_eps_value=20)
    assert not (tmp_path / "metrics.csv").exists()
    runner.run(sc, "fixed", 4, out_dir=tmp_path, k_eps_value=20, overwrite=True)
    assert (tmp_path / "results.csv").read_text() == "mine" and (tmp_path / "metrics.csv").exists()


def test_what_counts_as_a_directory_of_fempdls(tmp_path):
    """What fempdl recorded writing (runs, a scene's tradeoff folder beside them with its reports), its
    lock and hidden files are fempdl's or harmless; a visible file it did not record is yours, even
    one of a name fempdl writes, and the message shows a few names."""
    base = tmp_path / "scene"
    (base / "tradeoff" / "k1").mkdir(parents=True)
    (base / "tradeoff" / "k1" / "metrics.csv").write_text("epoch\n")
    files.record(base / "tradeoff" / "k1", "metrics.csv")
    (base / "tradeoff" / "metric_vs_cost.png").write_bytes(b"")
    files.record(base / "tradeoff", "metric_vs_cost.png")
    (base / ".git").mkdir()
    (base / ".lock").write_text("")
    assert rundir.foreign_entries(base) == []
    rundir.check_output_directory(base, resume=False, overwrite=False)
    (base / "tradeoff" / "k1" / "metrics.json").write_text("[]")            # not recorded: yours
    assert rundir.foreign_entries(base) == ["tradeoff/k1/metrics.json"]
    (base / "tradeoff" / "k1" / "metrics.json").unlink()
    for name in ("a.txt", "b.txt", "c.txt", "d.txt"):
        (base / name).write_text("")
    with pytest.raises(rundir.RunDirectoryError, match=r"files fempdl did not write \(a.txt, b.txt, c.txt, ... "
                                                       r"\(4 entries\)\)"):
        rundir.check_output_directory(base, resume=False, overwrite=False)


def test_only_fempdls_temporary_files_are_removed(tmp_path):
    """Any hidden '.*.*.tmp' file was deleted on start, a user's too."""
    ours, yours = tmp_path / ".checkpoint.pt.0a1b2c3d.tmp", tmp_path / ".notes.draft.tmp"
    ours.write_bytes(b"")
    yours.write_text("mine")
    assert checkpoints.remove_stale_temporaries(tmp_path) == [ours]
    assert yours.read_text() == "mine"


# ------------------------------------------------------------------ damaged checkpoints
@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A scene file and a run directory holding one finished 2-epoch run (out/k4)."""
    return finished_run(tmp_path_factory.mktemp("trained"), SCENE)


def _junk_file(path):
    path.write_bytes(b"\x80\x02GA")          # a pickle opcode whose argument is cut off: struct.error


def _bytes_overwritten(path):
    """Four bytes of the torch RNG state changed inside the zip: it loaded, and trained on."""
    data = path.read_bytes()
    at = data.find(torch.load(path, weights_only=True)["rng"]["torch"].numpy().tobytes()[:64]) + 100
    path.write_bytes(data[:at] + b"\x13\x37\xbe\xef" + data[at + 4:])


def _edited(edit):
    def damage(path):
        state = torch.load(path, weights_only=True)
        edit(state)
        torch.save(state, path)
    return damage


DAMAGES = {
    "junk-4-bytes": (_junk_file, "is unreadable or incomplete (BadZipFile: File is not a zip file)"),
    "4-bytes-overwritten": (_bytes_overwritten, "is damaged (its part"),
    "rng-state": (_edited(lambda s: s["rng"]["numpy"].update(keys=[1, 2])),        # IndexError before
                  "is malformed (rng holds numpy or python generator states out of their ranges)"),
    "layer-stats": (_edited(lambda s: s["layer_stats_by_rank"][0].__setitem__(0, [1, 2])),   # AttributeError
                    "is malformed (layer_stats_by_rank holds an entry that is not a dict of counters)"),
    "stats-value": (_edited(lambda s: s["layer_stats_by_rank"][0][0].update(forward_iterations=None)),
                    "record of the layers' counters does not fit this run's (ValueError: layer 0's counter "
                    "forward_iterations is None"),
    "metric-row": (_edited(lambda s: s["rows"][0].update(bogus=1.0)),          # refused by the CSV writer
                   "is malformed (metric row 0 has unknown keys 'bogus')"),
}


@pytest.mark.parametrize("damage", list(DAMAGES))
def test_a_damaged_checkpoint_is_one_line_naming_the_file(trained, tmp_path, capsys, damage):
    path, done = trained
    out = tmp_path / "out"
    shutil.copytree(done, out)
    checkpoint = out / "k4" / checkpoints.CHECKPOINT
    damage_file, fragment = DAMAGES[damage]
    damage_file(checkpoint)
    line = one_line_error(run_argv(path, out, "--resume", "--epochs", 3), capsys)
    assert f"checkpoint {str(checkpoint)!r} {fragment}" in line or f"{checkpoint}: its {fragment}" in line, line


# ------------------------------------------------------------------ PETSc options refused at set-up
def test_an_option_petsc_rejects_only_at_set_up_is_named(coarse_lshape):
    """pc_factor_mat_solver_type = "nonexistent" raised PETSc.Error 92 with PETSc's C stack."""
    from petsc4py import PETSc

    from fempdl import forms
    from fempdl.bridge_torch import SolveLayer
    from fempdl.ksp_adjoint import KSPOptions

    prob = forms.poisson.problem(coarse_lshape, controls=("f",))
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    bad = SolveLayer(prob, KSPOptions.preset("lu", petsc_options={"pc_factor_mat_solver_type": "nonexistent"}))
    with pytest.raises(ValueError, match=r"petsc_options\['pc_factor_mat_solver_type'\] = 'nonexistent' was "
                                         r"rejected by PETSc when the solver was set up \(ksp_type='preonly', "
                                         r"pc_type='lu'; PETSc error code 92: Could not locate solver type "
                                         r"nonexistent.*; give a value this PETSc build takes for it"):
        bad(f=f)
    bad.close()
    assert not [key for key in PETSc.Options().getAll() if "probe" in key]      # the probes left nothing
    good = SolveLayer(prob, KSPOptions.preset("lu", petsc_options={"pc_factor_mat_solver_type": "petsc"}))
    assert torch.isfinite(good(f=f)).all()
    good.close()


def test_a_newton_inner_option_petsc_rejects_at_set_up_is_named(coarse_lshape):
    """The same option on a Newton layer's inner solve, which SNES sets up: PETSc.Error 92 before."""
    from fempdl import NewtonOptions, NonlinearSolveLayer, forms
    from fempdl.ksp_adjoint import KSPOptions

    prob = forms.nonlinear_diffusion.problem(coarse_lshape, controls=("f",))
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    inner = KSPOptions.preset("lu", petsc_options={"pc_factor_mat_solver_type": "nonexistent"})
    bad = NonlinearSolveLayer(prob, NewtonOptions(ksp=inner))
    with pytest.raises(ValueError, match=r"petsc_options\['pc_factor_mat_solver_type'\] = 'nonexistent' was "
                                         r"rejected by PETSc when the solver was set up"):
        bad(f=f)
    bad.close()


# ------------------------------------------------------------------ threads, caps and seeds
def test_threads_beyond_the_cores_are_an_argument_error(capsys):
    """--threads 100000 ended in a traceback from gmsh (or MPI failing to start)."""
    with pytest.raises(SystemExit) as info:
        cli.build_parser().parse_args(["run", "--threads", "100000"])
    err = capsys.readouterr().err
    assert info.value.code == 2 and "argument --threads: must be at most" in err and "cores" in err, err
    cores = cli.usable_cores()
    assert cli.build_parser().parse_args(["run", "--threads", str(cores)]).threads == cores
    with pytest.raises(argparse.ArgumentTypeError, match="must be >= 1"):
        cli.thread_count("0")


@pytest.mark.parametrize("args, fragment", [
    (["--k", "99999999999"], "--k 99999999999 cannot cap the solver of scene 'hostile-app': max_it must be <="),
    (["--set", "prdp.k0=3000000000"], "[prdp] k0 = 3000000000 cannot cap the solver of scene 'hostile-app'"),
], ids=["k", "prdp-k0"])
def test_a_cap_beyond_petsc_int_is_refused_before_anything_trains(scene_file, tmp_path, capsys, args, fragment):
    """It was refused only after the baseline had trained (143 epochs of heat-emulator-2d)."""
    out = tmp_path / "out"
    line = one_line_error(["run", scene_file, "--out", out, "--no-progress", *args], capsys)
    assert fragment in line, line
    assert not out.exists()                                     # no baseline, no directory


def test_runner_run_checks_its_cap_and_seed_first(tmp_path):
    sc = scene.parse(SCENE)
    with pytest.raises(ValueError, match=r"k=99999999999 cannot cap the solver of scene 'hostile-app'"):
        runner.run(sc, "fixed", 99999999999, out_dir=tmp_path / "k")
    with pytest.raises(ValueError, match=r"seed must be an int in \[0, 2\^63 - 1\]"):
        runner.run(sc, "fixed", 4, k_eps_value=20, out_dir=tmp_path / "seed", seed=2 ** 70)
    assert not (tmp_path / "k").exists() and not (tmp_path / "seed").exists()


@pytest.mark.parametrize("where", ["file", "set"])
def test_a_seed_beyond_the_generators_in_a_scene_is_refused(tmp_path, capsys, where):
    """[data] seed = 2^70 said "Overflow when unpacking long long" (a traceback from torch.manual_seed)."""
    text = tiny_scene("emulator", name="big-seed", optimizer={"epochs": 1},
                      data={"seed": 2 ** 70} if where == "file" else {})
    path = tmp_path / "seed.toml"
    path.write_text(text)
    extra = ["--set", f"data.seed={2 ** 70}"] if where == "set" else []
    line = one_line_error(["run", path, "--out", tmp_path / "out", "--no-progress", *extra], capsys)
    assert f"[data] seed must be <= {2 ** 63 - 1}, got {2 ** 70}" in line, line
    assert scene.parse(tiny_scene("emulator", data={"seed": 2 ** 63 - 1})).data.seed == 2 ** 63 - 1
