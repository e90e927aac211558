"""Run directories under hostile conditions: files of yours that look like a run's, a --resume asking
for other runs, a lock or checkpoint that is a link or a device, and files that cannot be written.
Each ends in one clear error that names the input and the fix, with nothing of yours replaced."""
from __future__ import annotations

import os
import shutil

import pytest
import torch

from fempdl.app import cli, scene
from fempdl.app.runs import checkpoints, files, rundir, runner

from helpers import finished_run, one_line_error, tiny_scene

SCENE = tiny_scene("inverse", name="app-safety", optimizer={"epochs": 2})


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A scene file and a directory holding one finished 2-epoch run of `fempdl run --k 4 --no-baseline`."""
    return finished_run(tmp_path_factory.mktemp("trained"), SCENE)


def run_argv(scene_file, out, *extra, k=4):
    return ["run", scene_file, *(["--k", k] if k else []), "--out", out, "--no-progress", "--no-baseline", *extra]


def copy_of(trained, tmp_path):
    path, done = trained
    out = tmp_path / "out"
    shutil.copytree(done, out, symlinks=True)
    return path, out


def listing(directory):
    return sorted(str(p.relative_to(directory)) for p in directory.rglob("*"))


# ------------------------------------------------------------------ files of yours that look like a run's
@pytest.mark.parametrize("where", ["", "k4/"], ids=["top", "one-folder-down"])
@pytest.mark.parametrize("name", ["metrics.csv", "metrics.json", "checkpoint.pt"])
def test_your_run_like_files_are_no_run_and_resume_replaces_nothing(tmp_path, capsys, name, where):
    """A folder of your metrics.csv (or metrics.json, checkpoint.pt) and time_split.png was taken for an
    earlier run: the refusal recommended --resume, which then replaced time_split.png."""
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    out = tmp_path / "mine"
    (out / where).mkdir(parents=True, exist_ok=True)
    (out / where / name).write_bytes(b"my numbers")
    (out / "time_split.png").write_bytes(b"my plot")
    before = listing(out)
    for extra in ([], ["--resume"]):
        line = one_line_error(run_argv(path, out, *extra), capsys)
        assert (f"{str(out)!r} holds no fempdl run but files fempdl did not write ({where}{name}, time_split.png); "
                "runs write into a new or empty directory or one of their own: choose another --out, or pass "
                "--overwrite") in line, line
        assert "--resume" not in line, line
    assert listing(out) == before                                   # nothing written, not even a record
    assert (out / where / name).read_bytes() == b"my numbers" and (out / "time_split.png").read_bytes() == b"my plot"


def test_the_runner_does_not_resume_your_metrics(tmp_path):
    (tmp_path / "metrics.csv").write_text("mine")
    with pytest.raises(rundir.RunDirectoryError, match=r"holds no fempdl run but files fempdl did not write "
                                                       r"\(metrics.csv\); .* choose another out_dir, or pass "
                                                       r"overwrite=True"):
        runner.run(scene.parse(SCENE), "fixed", 4, out_dir=tmp_path, k_eps_value=20, resume=True)
    assert (tmp_path / "metrics.csv").read_text() == "mine" and not (tmp_path / files.RECORD).exists()


def test_a_run_beside_files_of_yours_resumes_once_they_are_moved_out(trained, tmp_path, capsys):
    path, out = copy_of(trained, tmp_path)
    (out / "notes.txt").write_text("mine")
    line = one_line_error(run_argv(path, out, "--resume", "--epochs", 3), capsys)
    assert (f"{str(out)!r} holds an earlier run and files fempdl did not write (notes.txt); move those out and "
            "pass --resume to continue the run, or choose another --out") in line, line
    (out / "notes.txt").unlink()
    assert cli.main([str(a) for a in run_argv(path, out, "--resume", "--epochs", 3)]) == 0
    assert len(checkpoints.load(out / "k4" / checkpoints.CHECKPOINT)["rows"]) == 3


# ------------------------------------------------------------------ --resume asking for other runs
@pytest.mark.parametrize("k, extra, fragment", [
    (8, [], "k was 4, now 8"),
    (None, ["--prdp"], "mode was fixed K=4, now prdp"),
    (None, [], "mode was fixed K=4, now prdp"),
    (None, ["--converged"], "mode was fixed K=4, now converged; the baseline was skipped (--no-baseline), now "
                            "trained"),
], ids=["k", "prdp", "default-mode", "converged"])
def test_resume_asking_for_other_runs_is_refused_naming_what_differs(trained, capsys, k, extra, fragment):
    """--resume --k 8 (or --prdp) after --k 4 quietly started a new run (exit 0)."""
    path, out = trained
    before = listing(out)
    line = one_line_error(run_argv(path, out, "--resume", *extra, k=k), capsys)
    assert (f"--resume continues the runs in {str(out)!r} as they were started, and {fragment}: continue them "
            "with `fempdl run --k 4 --no-baseline --resume`, or start the new runs in another --out") in line, line
    assert listing(out) == before                       # no run started


def test_resume_with_the_baseline_added_is_refused(trained, capsys):
    path, out = trained
    argv = [a for a in run_argv(path, out, "--resume") if a != "--no-baseline"]
    line = one_line_error(argv, capsys)
    assert "the baseline was skipped (--no-baseline), now trained" in line, line


# ------------------------------------------------------------------ the lock file
def test_a_lock_that_is_a_symbolic_link_is_neither_written_through_nor_deleted(tmp_path, capsys):
    """`ln -s ~/precious DIR/.lock` got precious overwritten with "host pid" and the link removed."""
    precious, run = tmp_path / "precious", tmp_path / "run"
    precious.write_text("precious")
    run.mkdir()
    (run / rundir.LOCK).symlink_to(precious)
    with pytest.raises(rundir.RunDirectoryError, match=(
            rf"the lock file '{run / rundir.LOCK}' is a symbolic link, not a file fempdl created, so it is neither "
            rf"written nor deleted; remove it yourself if no run uses '{run}', or choose another output directory")):
        rundir.RunLock(run).acquire()
    assert precious.read_text() == "precious" and (run / rundir.LOCK).is_symlink()
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    line = one_line_error(run_argv(path, run), capsys)
    assert "is a symbolic link, not a file fempdl created" in line, line
    assert precious.read_text() == "precious" and (run / rundir.LOCK).is_symlink()


def test_a_dangling_lock_link_creates_nothing(tmp_path):
    """Created through the link, the lock would have been a new file wherever the link points."""
    run, target = tmp_path / "run", tmp_path / "elsewhere"
    run.mkdir()
    (run / rundir.LOCK).symlink_to(target)
    with pytest.raises(rundir.RunDirectoryError, match="is a symbolic link, not a file fempdl created"):
        rundir.RunLock(run).acquire()
    assert not target.exists()


@pytest.mark.parametrize("make, kind", [(os.mkfifo, "a named pipe"), (os.mkdir, "a directory")],
                         ids=["fifo", "directory"])
def test_a_lock_that_is_no_regular_file_is_refused(tmp_path, make, kind):
    make(tmp_path / rundir.LOCK)
    with pytest.raises(rundir.RunDirectoryError, match=f"the lock file '{tmp_path / rundir.LOCK}' is {kind}, not a "
                                                       "file fempdl created"):
        rundir.RunLock(tmp_path).acquire()
    assert os.path.lexists(tmp_path / rundir.LOCK)


def test_release_deletes_only_the_lock_itself(tmp_path):
    """A link put in the lock's place, even one to the lock's own file, is not the lock: it stays."""
    run = tmp_path / "run"
    lock = rundir.RunLock(run)
    lock.acquire()
    os.link(run / rundir.LOCK, tmp_path / "second-name")
    (tmp_path / "link").symlink_to(tmp_path / "second-name")
    os.replace(tmp_path / "link", run / rundir.LOCK)
    lock.release()
    assert (run / rundir.LOCK).is_symlink()


# ------------------------------------------------------------------ checkpoints that are no file fempdl wrote
@pytest.fixture
def unread(monkeypatch):
    """Reading the checkpoint fails the test at once (never reads /dev/zero to the end, nor waits on a pipe)."""
    def read(*args, **kwargs):
        raise AssertionError("the checkpoint was read")
    monkeypatch.setattr(checkpoints.zipfile, "ZipFile", read)
    monkeypatch.setattr(checkpoints.torch, "load", read)


@pytest.mark.parametrize("make, kind", [(lambda p: p.symlink_to("/dev/zero"), "a character device"),
                                        (os.mkfifo, "a named pipe")], ids=["dev-zero", "fifo"])
def test_a_checkpoint_that_is_no_regular_file_is_refused_unread(trained, tmp_path, capsys, unread, make, kind):
    """A checkpoint linked to /dev/zero grew the process to 24 GB until it was killed."""
    path, out = copy_of(trained, tmp_path)
    checkpoint = out / "k4" / checkpoints.CHECKPOINT
    checkpoint.unlink()
    make(checkpoint)
    line = one_line_error(run_argv(path, out, "--resume", "--epochs", 3), capsys)
    assert f"checkpoint {str(checkpoint)!r} is {kind}, not a file fempdl wrote, and is not read; to continue: " \
           "start the run afresh" in line, line


def test_a_checkpoint_larger_than_the_run_could_write_is_refused_unread(trained, tmp_path, capsys, unread):
    path, out = copy_of(trained, tmp_path)
    checkpoint = out / "k4" / checkpoints.CHECKPOINT
    os.truncate(checkpoint, 1 << 40)                        # sparse: a terabyte that takes no space
    line = one_line_error(run_argv(path, out, "--resume", "--epochs", 3), capsys)
    assert f"checkpoint {str(checkpoint)!r} is 1.0 TiB, more than a checkpoint of this run can be (256.0 MiB)" \
           in line, line


# ------------------------------------------------------------------ files that cannot be written
def failing_save(monkeypatch, after: int = 0):
    """torch.save fails as on a full disk, after ``after`` calls that succeed."""
    real, calls = torch.save, []

    def save(*args, **kwargs):
        calls.append(1)
        if len(calls) > after:
            raise RuntimeError("PytorchStreamWriter failed writing file data/0: file write failed")
        return real(*args, **kwargs)
    monkeypatch.setattr(torch, "save", save)


def test_a_first_checkpoint_that_cannot_be_written_leaves_nothing_to_resume(tmp_path, capsys, monkeypatch):
    """The advice was --resume, which started afresh."""
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    out = tmp_path / "out"
    failing_save(monkeypatch)
    line = one_line_error(run_argv(path, out), capsys)
    assert (f"cannot write the run's files in {str(out / 'k4')!r} (PytorchStreamWriter failed writing file data/0: "
            "file write failed); no checkpoint was saved, so there is nothing to resume: free some space on its file "
            "system or make it writable, then start the run again") in line, line
    assert "--resume" not in line and not rundir.holds_run(out)
    monkeypatch.undo()
    assert cli.main([str(a) for a in run_argv(path, out)]) == 0             # started again, as advised


def test_a_later_checkpoint_that_cannot_be_written_resumes_from_the_last(tmp_path, monkeypatch):
    sc = scene.parse(SCENE)
    failing_save(monkeypatch, after=1)
    with pytest.raises(rundir.RunDirectoryError, match=r"\(PytorchStreamWriter failed writing file data/0: file "
                                                       r"write failed\); its checkpoint after epoch 1 is kept: free "
                                                       r"some space .* continue the run with --resume"):
        runner.run(sc, "fixed", 4, out_dir=tmp_path, k_eps_value=20, checkpoint_every=0.0)
    monkeypatch.undo()
    assert len(runner.run(sc, "fixed", 4, out_dir=tmp_path, k_eps_value=20, resume=True).rows) == 2


def test_resume_of_another_commands_runs_is_refused(tmp_path, capsys):
    """A tradeoff sweep's folder is not continued by `fempdl run --resume`, and `fempdl tradeoff` has no
    --resume to suggest."""
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    out = tmp_path / "tradeoff"
    (out / "k4").mkdir(parents=True)
    files.write_recorded(out / "k4" / "metrics.csv", lambda p: p.write_text("epoch\n"))
    files.record_command(out, {"command": "tradeoff"})
    line = one_line_error(run_argv(path, out, "--resume"), capsys)
    assert (f"--resume continues the runs in {str(out)!r} as they were started, and they are of `fempdl tradeoff`, "
            "not `fempdl run`: start the new runs in another --out") in line, line


@pytest.mark.parametrize("checkpoint", [False, True])
def test_ctrl_c_advises_resume_only_when_a_checkpoint_was_kept(tmp_path, monkeypatch, capsys, checkpoint):
    """Interrupted before a run's first checkpoint there is nothing to continue: --resume would start afresh."""
    from fempdl.app import commands
    from fempdl.app.runs import files

    def interrupted(args, sc, out):
        if checkpoint:
            (out / "k4").mkdir()
            files.write_recorded(out / "k4" / "checkpoint.pt", lambda p: p.write_bytes(b"epochs"))
        raise KeyboardInterrupt

    monkeypatch.setattr(commands, "_command", interrupted)
    path = tmp_path / "tiny.toml"
    path.write_text(SCENE)
    assert cli.main([str(a) for a in run_argv(path, tmp_path / "out")]) == 130
    err = capsys.readouterr().err
    if checkpoint:
        assert "fempdl: interrupted; a run's checkpoint holds its epochs finished" in err
        assert "(continue with --resume)" in err
    else:
        assert "fempdl: interrupted; no checkpoint was written yet, so there is nothing to resume: run the " \
               "command again" in err
