"""Hostile and careless inputs: tampered and corrupt checkpoints, resumes of another run, shared output
directories, names that would become paths, sizes beyond the machine, and solver options that would
silently go wrong. Every case must end in a clear error (or warning) and never run foreign code."""
from __future__ import annotations

import contextlib
import io
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from mpi4py import MPI
import pytest
import torch

from fempdl import forms, mesh
from fempdl.app import cli, scene
from fempdl.app.runs import checkpoints, files, rundir, runner
from fempdl.app.runs.checkpoints import CheckpointError
from fempdl.ksp_adjoint import KSPOptions

from helpers import tiny_scene


def inverse_text(**sections) -> str:
    return tiny_scene("inverse", {"scene": {"name": "hostile-inverse"}, "optimizer": {"epochs": 6}}, **sections)


INVERSE = inverse_text()


def inverse(text: str = INVERSE) -> scene.Scene:
    return scene.parse(text)


def train(out: Path, sc: scene.Scene | None = None, **kwargs):
    return runner.run(sc or inverse(), "fixed", 4, out_dir=out, k_eps_value=20, **kwargs)


def call(argv) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in argv])
    return code, err.getvalue()


# ------------------------------------------------------------------ checkpoints
class _Payload:
    """Unpickling this object would run a shell command that creates ``marker``."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return os.system, (f"touch {self.marker}",)


def test_a_checkpoint_that_would_run_code_is_refused_and_nothing_runs(tmp_path):
    out, marker = tmp_path / "run", tmp_path / "pwned"
    train(out, stop_after=2)
    state = torch.load(out / "checkpoint.pt", weights_only=True)
    state["prdp"] = _Payload(marker)
    torch.save(state, out / "checkpoint.pt")
    with pytest.raises(CheckpointError, match=r"holds objects other than tensors and plain values \(it refers to "
                                              r"GLOBAL posix.system\)"):
        train(out, resume=True)
    assert not marker.exists()
    # The command says the same and exits 2.
    path = tmp_path / "hostile.toml"
    path.write_text(INVERSE)
    (tmp_path / "cli" / "converged").mkdir(parents=True)
    torch.save({"model": _Payload(marker)}, tmp_path / "cli" / "converged" / "checkpoint.pt")
    files.record(tmp_path / "cli" / "converged", "checkpoint.pt")     # as if fempdl had written it
    files.record_command(tmp_path / "cli", {"command": "run", "mode": "fixed", "k": 4, "baseline": True})
    code, err = call(["run", path, "--k", 4, "--out", tmp_path / "cli", "--resume", "--no-progress"])
    assert code == 2 and "holds objects other than tensors" in err
    assert not marker.exists()


def test_checkpoints_hold_only_tensors_and_plain_values(tmp_path):
    train(tmp_path, stop_after=2)
    state = torch.load(tmp_path / "checkpoint.pt", weights_only=True)     # would raise on any other object
    assert isinstance(state["rng"]["numpy"]["keys"], list) and len(state["rng"]["numpy"]["keys"]) == 624
    assert isinstance(state["rng"]["python"]["state"], list)
    with pytest.raises(TypeError, match=r"checkpoint\['bad'\] is a _Payload"):
        checkpoints.plain({"bad": _Payload(tmp_path)})


@pytest.mark.parametrize("damage", ["truncated", "empty", "text", "no-model"])
def test_a_corrupt_checkpoint_gives_one_error_naming_the_file_and_the_remedy(tmp_path, damage):
    train(tmp_path, stop_after=2, checkpoint_every=0.0)     # a previous checkpoint to name
    path = tmp_path / "checkpoint.pt"
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "empty":
        path.write_bytes(b"")
    elif damage == "text":
        path.write_text("not a checkpoint")
    else:
        state = torch.load(path, weights_only=True)
        del state["model"]
        torch.save(state, path)
    with pytest.raises(CheckpointError) as info:
        train(tmp_path, resume=True)
    message = str(info.value)
    assert str(path) in message and "start the run afresh" in message
    assert f"mv {tmp_path / 'checkpoint.prev.pt'} {path}" in message


def test_the_previous_checkpoint_is_kept_and_restores(tmp_path):
    whole = train(tmp_path / "whole")
    out = tmp_path / "torn"
    train(out, stop_after=3, checkpoint_every=0.0)                # files after every epoch
    assert torch.load(out / "checkpoint.prev.pt", weights_only=True)["epoch"] == 1
    (out / "checkpoint.pt").write_bytes(b"")           # a torn write
    os.replace(out / "checkpoint.prev.pt", out / "checkpoint.pt")
    resumed = train(out, resume=True)
    assert [row["val_metric"] for row in resumed.rows] == [row["val_metric"] for row in whole.rows]


def test_stale_temporary_files_are_removed_and_files_follow_the_umask(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    stale = [out / ".checkpoint.pt.0a1b2c3d.tmp", out / ".metrics.json.k3j4h5g6"]   # new and mkstemp naming
    for path in stale:
        path.write_bytes(b"")
    keep = out / ".notes"
    keep.write_text("mine")
    old = os.umask(0o022)
    try:
        train(out, stop_after=1)
    finally:
        os.umask(old)
    assert not any(path.exists() for path in stale) and keep.exists()
    for name in ("metrics.csv", "metrics.json", "checkpoint.pt"):
        assert (out / name).stat().st_mode & 0o777 == 0o644
    assert not list(out.glob(".*.tmp"))


# ------------------------------------------------------------------ resume of another run
def test_resume_refuses_a_changed_scene_and_names_the_keys(tmp_path):
    train(tmp_path, stop_after=2)
    changed = inverse(inverse_text(inverse={"theta_ref": [0.5, 1.9]}, optimizer={"lr": 0.5}))
    with pytest.raises(rundir.ResumeError) as info:
        train(tmp_path, changed, resume=True)
    message = str(info.value)
    assert "run.scene.inverse.theta_ref: [0.6, 1.9] -> [0.5, 1.9]" in message
    assert "run.scene.optimizer.lr: 1.0 -> 0.5" in message and "--overwrite" in message
    with pytest.raises(rundir.ResumeError, match=r"run.k: 4 -> 5"):
        runner.run(inverse(), "fixed", 5, out_dir=tmp_path, k_eps_value=20, resume=True)


def test_resume_may_change_the_number_of_epochs(tmp_path):
    train(tmp_path, stop_after=2)
    longer = inverse(inverse_text(optimizer={"epochs": 8}))
    assert len(train(tmp_path, longer, resume=True).rows) == 8


# ------------------------------------------------------------------ output directories
def test_a_directory_locked_by_a_live_process_is_refused(tmp_path):
    sleeper = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        tmp_path.joinpath(rundir.LOCK).write_text(f"{socket.gethostname()} {sleeper.pid}\n")
        with pytest.raises(rundir.RunDirectoryError, match=f"in use by another run \\(process {sleeper.pid}"):
            train(tmp_path)
        assert not (tmp_path / "checkpoint.pt").exists()
    finally:
        sleeper.kill()
        sleeper.wait()
    # Its process is gone: the lock is stale, taken over, and removed after the run.
    train(tmp_path, stop_after=1)
    assert (tmp_path / "checkpoint.pt").exists() and not (tmp_path / rundir.LOCK).exists()


def test_the_command_refuses_a_directory_holding_a_run_unless_resume_or_overwrite(tmp_path):
    path = tmp_path / "hostile.toml"
    path.write_text(INVERSE)
    out = tmp_path / "out"
    base = ["run", path, "--k", 4, "--out", out, "--no-progress", "--no-baseline"]
    assert call(base)[0] == 0
    code, err = call(base)
    assert code == 2 and "holds the files of an earlier run; pass --resume" in err
    assert call(base + ["--overwrite"])[0] == 0
    assert call(base + ["--resume"])[0] == 0
    assert call(base + ["--resume", "--overwrite"])[0] == 2
    assert not (out / rundir.LOCK).exists()
    path.write_text(inverse_text(inverse={"theta_ref": [0.6, 2.0]}))
    code, err = call(base + ["--resume"])
    assert code == 2 and "was written by a different run; changed since: run.scene.inverse.theta_ref" in err


@pytest.mark.parametrize("name", ["../../../x", "/tmp/x", "..", "a/b", "", "x" * 129, "na me"])
def test_scene_names_that_are_not_slugs_are_refused(name):
    text = inverse_text(name=name)
    with pytest.raises(scene.SceneError, match=r"\[scene\] name must be 1-128 letters"):
        scene.parse(text)
    with pytest.raises(ValueError):
        rundir.child(Path("runs"), name)


def test_a_scene_file_that_is_not_utf8_is_a_scene_error(tmp_path):
    path = tmp_path / "latin1.toml"
    path.write_bytes(inverse_text(name="hostile").encode() + "# caf\xe9\n".encode("latin-1"))
    with pytest.raises(scene.SceneError, match="not a UTF-8 text file"):
        scene.load(path)


# ------------------------------------------------------------------ sizes beyond the machine
@pytest.mark.parametrize("h", [1e-12, 1e-8])
def test_a_mesh_size_beyond_the_cell_budget_is_refused_with_the_estimate(h):
    with pytest.raises(ValueError, match=r"would mesh 'lshape' into about 7e\+\d+ cells, more than max_cells"):
        mesh.load("lshape", MPI.COMM_SELF, h=h)


def test_a_mesh_size_beyond_the_geometry_is_refused():
    with pytest.raises(ValueError, match=r"larger than the shortest feature of 'obstacle' \(0.41\)"):
        mesh.load("obstacle", MPI.COMM_SELF, h=1.0)


@pytest.mark.parametrize("section,key,value", [("network", "hidden", 10 ** 9), ("data", "train", 10 ** 12)])
def test_scene_sizes_beyond_memory_are_scene_errors_with_the_estimate(section, key, value):
    text = tiny_scene(**{section: {key: value}})
    with pytest.raises(scene.SceneError, match=r"the scene needs about [\d.]+ [TPG]iB .* more than the memory budget"):
        scene.parse(text)


def test_more_modes_than_the_mesh_resolves_is_a_scene_error():
    with pytest.raises(scene.SceneError, match=r"\[data\] modes = 1000000 gives 1000000\^2 sine modes"):
        scene.parse(tiny_scene(data={"modes": 1000000}))


# ------------------------------------------------------------------ solver options
def test_preonly_without_a_factorisation_is_refused():
    with pytest.raises(ValueError, match=r"ksp_type='preonly' applies the preconditioner once.*pc_type='jacobi'"):
        KSPOptions(ksp_type="preonly", pc_type="jacobi")
    assert KSPOptions(ksp_type="preonly", pc_type="cholesky").direct


@pytest.mark.parametrize("field", ["max_it", "gmres_restart"])
def test_iteration_counts_beyond_petsc_int_are_refused(field):
    extra = {"ksp_type": "gmres"} if field == "gmres_restart" else {}
    with pytest.raises(ValueError, match=rf"{field} must be <= 2147483647 \(the largest PETSc int"):
        KSPOptions(**extra, **{field: 2 ** 31})


def test_a_non_numeric_petsc_option_names_the_option(coarse_problems):
    from fempdl.bridge_torch import SolveLayer
    opts = KSPOptions(max_it=5, petsc_options={"ksp_richardson_scale": "abc", "ksp_view": None})
    with pytest.raises(ValueError, match=r"petsc_options\['ksp_richardson_scale'\] = 'abc' was rejected by PETSc"):
        SolveLayer(coarse_problems["poisson"], opts)


@pytest.mark.parametrize("kappa", [0.0, -1.0, lambda x: x[0]])
@pytest.mark.parametrize("pde", ["poisson", "heat"])
def test_a_nonpositive_kappa_is_refused(pde, kappa):
    msh = mesh.load("lshape", MPI.COMM_SELF, h=0.5)
    with pytest.raises(ValueError, match=r"kappa must be > 0 everywhere .* got a minimum of"):
        getattr(forms, pde).problem(msh, kappa=kappa)


_INTERRUPTED_SOLVE = """
import os, signal, threading, torch
from mpi4py import MPI
from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
layer = SolveLayer(forms.poisson.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.1)),
                   KSPOptions(max_it=10 ** 9, engine="petsc"))
f = torch.ones(2, layer.problem.control_size("f"), dtype=torch.float64)
threading.Timer(1.0, lambda: os.kill(os.getpid(), signal.SIGINT)).start()
try:
    layer(f=f)
except KeyboardInterrupt:
    print("interrupted after", layer.system._solver.ksp.getIterationNumber(), "iterations")
"""


def _interruptible_child() -> None:
    """A child's SIGINT as a terminal gives it: unblocked, default disposition (Python then installs
    KeyboardInterrupt). Both are inherited across fork and exec, and a library in this test process
    (a thread that blocked SIGINT, a launcher that ignores it) must not make Ctrl-C look ignored."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def test_ctrl_c_stops_a_long_petsc_solve():
    """The solve would take hours: SIGINT after a second must end it with KeyboardInterrupt."""
    done = subprocess.run([sys.executable, "-c", _INTERRUPTED_SOLVE], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}, preexec_fn=_interruptible_child)
    assert done.returncode == 0, done.stderr
    iterations = int(done.stdout.split("after")[1].split()[0])
    assert 0 < iterations < 10 ** 9


# ------------------------------------------------------------------ unrolled memory
def _graph_nodes(tensor: torch.Tensor) -> int:
    seen, stack = set(), [tensor.grad_fn]
    while stack:
        node = stack.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        stack.extend(next_node for next_node, _ in node.next_functions)
    return len(seen)


@pytest.mark.parametrize("control", ["f", "kappa"])
def test_max_unrolled_values_bounds_what_the_forward_pass_keeps(coarse_problems, control):
    """With max_unrolled_values at the least checkpointed size, the floats saved for the backward
    pass (saved-tensor hooks) stay within it, where the unbounded solve keeps K steps' worth
    (measured RSS: benchmarks/bench_bounds.py); the gradient is unchanged."""
    from fempdl.bridge_torch import SolveLayer
    from fempdl.iterative import unrolled
    prob = coarse_problems["poisson"]
    K, batch = 400, 2
    n = prob.output_size
    m = torch.rand(batch, prob.control_size(control), dtype=torch.float64,
                   generator=torch.Generator().manual_seed(0)) + 0.5
    w = torch.randn(batch, n, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    method, opts = ("cg", KSPOptions.preset("cg", max_it=K)) if control == "f" else ("jacobi", KSPOptions(max_it=K))
    matrix_grad = control == "kappa"
    least = unrolled.checkpointed_values(method, K, n, batch, matrix_grad=matrix_grad)
    grads, kept = [], []
    for limit in (None, least):
        x = m.clone().requires_grad_()
        seen = {}

        def pack(t, seen=seen):
            if t.dim() == 2 and t.shape[0] >= n:           # (n, B) blocks and matrix-entry blocks
                seen[t.untyped_storage().data_ptr()] = t.untyped_storage().nbytes() // 8
            return t
        with torch.autograd.graph.saved_tensors_hooks(pack, lambda t: t):
            u = SolveLayer(prob, opts, diff="unrolled", max_unrolled_values=limit)(**{control: x})
        kept.append(sum(seen.values()))
        (u * w).sum().backward()
        grads.append(x.grad)
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-12, atol=1e-14)
    stored = unrolled.stored_values(method, K, n, batch, matrix_grad=matrix_grad)
    assert kept[0] >= 0.5 * stored and kept[1] <= least < stored / 5


def test_an_unrolled_solve_beyond_the_memory_budget_is_refused_up_front(coarse_problems):
    from fempdl.bridge_torch import SolveLayer
    from fempdl.iterative import unrolled
    prob = coarse_problems["poisson"]
    f = torch.ones(2, prob.control_size("f"), dtype=torch.float64, requires_grad=True)
    layer = SolveLayer(prob, KSPOptions.preset("cg", max_it=2 * 10 ** 9), diff="unrolled")
    with pytest.raises(MemoryError, match=r"K=2000000000.* would keep about [\d.]+ [TP]iB for the backward pass, "
                                          r"more than the memory budget .* max_unrolled_values below"):
        layer(f=f)
    with torch.no_grad():                                    # nothing is stored: nothing to refuse
        SolveLayer(prob, KSPOptions.preset("cg", max_it=3), diff="unrolled")(f=f)
    small = SolveLayer(prob, KSPOptions.preset("cg", max_it=50), diff="unrolled", memory_budget=4096)
    with pytest.raises(MemoryError, match=r"K=50, n=\d+, B=2 would keep about .* budget of 4.0 KiB"):
        small(f=f)
    A = torch.eye(4, dtype=torch.float64).to_sparse_csr()
    R = torch.ones(4, 1, dtype=torch.float64, requires_grad=True)
    with pytest.raises(MemoryError, match=r"more than the memory budget of 1.0 KiB"):
        unrolled.solve("cg", A, None, R, 1000, memory_budget=1024)
    least = unrolled.checkpointed_values("cg", 1000, 4, 1)
    unrolled.solve("cg", A, None, R, 1000, max_values=least, memory_budget=2 ** 20)   # checkpointed: fits


def test_the_interrupt_monitor_is_installed_only_on_long_solves(coarse_problems):
    from fempdl.bridge_torch import SolveLayer
    from fempdl.core import tuning
    from fempdl.solve.options import DEFAULT_CONVERGED_MAX_IT
    prob = coarse_problems["poisson"]
    layer = SolveLayer(prob, KSPOptions(max_it=20, engine="petsc"))
    solver = layer.system._solver
    long_cap = -(-tuning.INTERRUPT_CHECK_MIN_WORK // prob.output_size)
    installed = []
    for options in (KSPOptions(max_it=20), KSPOptions(max_it=long_cap), KSPOptions(max_it=long_cap - 1),
                    KSPOptions(max_it=None), KSPOptions.preset("lu")):
        solver._set_interrupt_checks(solver.ksp, options)
        installed.append(len(solver.ksp.getMonitor() or ()))
    uncapped = DEFAULT_CONVERGED_MAX_IT * prob.output_size >= tuning.INTERRUPT_CHECK_MIN_WORK
    assert installed == [0, 1, 0, int(uncapped), 0]


def test_a_second_command_on_the_same_output_directory_is_refused_while_the_first_runs(tmp_path):
    path = tmp_path / "long.toml"
    path.write_text(inverse_text(optimizer={"epochs": 100000}))
    out = tmp_path / "out"
    argv = ["run", str(path), "--k", "4", "--out", str(out), "--no-progress", "--no-baseline"]
    # Its log goes to a file: a pipe read only at the end fills within a second of training, and a
    # child blocked writing its last words after Ctrl-C would never exit.
    log = tmp_path / "first.log"
    with open(log, "wb") as sink:
        first = subprocess.Popen([sys.executable, "-m", "fempdl.app.cli", *argv], stdout=subprocess.DEVNULL,
                                 stderr=sink, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"},
                                 preexec_fn=_interruptible_child)
    try:
        deadline = time.monotonic() + 120
        # The first run holds the lock, its owner written, while it trains (its files come a second in).
        lock = out / "k4" / rundir.LOCK
        while not (lock.exists() and lock.stat().st_size):
            assert first.poll() is None and time.monotonic() < deadline, log.read_text()[-2000:]
            time.sleep(0.1)
        code, err = call(argv + ["--overwrite"])
        assert code == 2 and f"in use by another run (process {first.pid}" in err
        assert first.poll() is None                              # untouched: still training
    finally:
        first.send_signal(signal.SIGINT)
        first.wait(timeout=60)
    assert not (out / rundir.LOCK).exists()                      # released on Ctrl-C
    err = log.read_text()
    assert first.returncode == 130 and "Traceback" not in err and "fempdl: interrupted;" in err, err[-2000:]


def test_an_output_directory_that_is_a_file_is_refused(tmp_path):
    path = tmp_path / "hostile.toml"
    path.write_text(INVERSE)
    (tmp_path / "taken").write_text("a file")
    code, err = call(["run", path, "--k", 4, "--out", tmp_path / "taken", "--no-progress", "--no-baseline"])
    assert code == 2 and "cannot use" in err and "as an output directory" in err
