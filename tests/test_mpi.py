"""Under mpirun: distributed layers and parallel training give the serial numbers.

The scripts in ``tests/mpi/`` run under ``mpirun -n 2`` (and ``-n 1`` for the
serial side) in a subprocess, with a timeout so that a hang fails the test
instead of stalling the suite, and write their results from rank 0; layer
results are compared in DOF-coordinate order.
"""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from petsc4py import PETSc

from fempdl.core import _dolfinx

from helpers import tiny_scene

SCRIPTS = Path(__file__).parent / "mpi"
EXAMPLES = Path(__file__).parent.parent / "tools"
TIMEOUT = 300
HYPRE = PETSc.Sys.hasExternalPackage("hypre")
MPI_ENV = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1", "OMP_NUM_THREADS": "1"}


def mpirun(ranks: int, script: str, *args: str, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    """``mpirun -n ranks python SCRIPT args`` (a script in tests/mpi, a path, or ``-m module``),
    with the launcher of the MPI that mpi4py uses (Open MPI's mpirun, or the venv's MPICH mpiexec)."""
    target = [script] if script == "-m" or os.path.isabs(script) else [str(SCRIPTS / script)]
    command = [*_dolfinx.mpi_launcher(), "-n", str(ranks), sys.executable, *target, *args]
    return subprocess.run(command, env=MPI_ENV, capture_output=True, text=True, timeout=timeout)


def on_one_and_two_ranks(script: str, out: Path, suffix: str, *args: str, timeout: float = TIMEOUT) -> dict:
    """{1: ..., 2: ...}: what ``script`` wrote to its output file (its last argument) run on 1 rank and on 2,
    read as JSON (``suffix`` ".json") or as an .npz's arrays."""
    results = {}
    for ranks in (1, 2):
        path = out / f"ranks{ranks}{suffix}"
        done = mpirun(ranks, script, *args, str(path), timeout=timeout)
        assert done.returncode == 0, done.stderr[-3000:]
        results[ranks] = json.loads(path.read_text()) if suffix == ".json" else dict(np.load(path))
    return results


@pytest.fixture(scope="module")
def layer_results(tmp_path_factory):
    return on_one_and_two_ranks("layer_gradients.py", tmp_path_factory.mktemp("mpi"), ".npz")


def test_the_mesh_is_split_over_two_ranks(layer_results):
    serial, split = layer_results[1]["owned_sizes"], layer_results[2]["owned_sizes"]
    assert len(serial) == 1 and len(split) == 2
    assert split.sum() == serial.sum() and split.min() > 0.3 * serial.sum()


@pytest.mark.parametrize("pde", ["poisson", "heat"])
@pytest.mark.parametrize("solver", ["lu", "jacobi", "cg", "gmres"])
def test_distributed_layer_equals_serial(layer_results, pde, solver):
    serial, split = layer_results[1], layer_results[2]
    keys = [k for k in serial if k.startswith(f"{pde}/{solver}/")]
    assert {f"{pde}/{solver}/u", f"{pde}/{solver}/grad_kappa"} <= set(keys)
    for key in keys:
        a, b = serial[key], split[key]
        assert a.shape == b.shape, key
        if key.endswith("forward_iterations"):
            # Capped solves run exactly K on any number of ranks; converged ones need the same count.
            assert int(a) == int(b), key
            continue
        assert np.abs(a - b).max() <= 1e-10 * np.abs(a).max(), key


def test_the_iterative_defaults_on_a_distributed_3d_mesh_equal_the_serial_ones(tmp_path):
    """CG + AMG and, inside Newton, GMRES + block Jacobi/ILU(0) (PCILU alone does not run in parallel):
    each solves to rtol 1e-10, so one and two ranks agree to that times the condition (~1e2 here)."""
    results = on_one_and_two_ranks("default_solver.py", tmp_path, ".npz")
    serial, split = results[1], results[2]
    assert str(serial["poisson/ksp"]) == str(split["poisson/ksp"]) == f"cg+{'hypre' if HYPRE else 'gamg'}"
    assert str(serial["newton/ksp"]) == str(split["newton/ksp"]) == "gmres+bjacobi"
    for key in [k for k in serial if not k.endswith("/ksp")]:
        a, b = serial[key], split[key]
        assert a.shape == b.shape, key
        assert np.abs(a - b).max() <= 1e-7 * np.abs(a).max(), key


def test_an_error_on_one_rank_ends_the_job_instead_of_hanging():
    done = mpirun(2, "injected_failure.py", timeout=60)  # a hang raises TimeoutExpired
    assert done.returncode != 0
    assert "[rank 1] RuntimeError: injected failure on rank 1" in done.stderr
    assert "[rank 1] aborting all 2 ranks" in done.stderr
    assert "unreachable" not in done.stdout


@pytest.fixture(scope="module", params=["data", "mesh", "mesh-warm"])
def training_results(request, tmp_path_factory):
    """Rows of the tiny scene trained in one parallel mode, on 1 rank and on 2."""
    out = tmp_path_factory.mktemp(f"training-{request.param}")
    return request.param, on_one_and_two_ranks("parallel_training.py", out, ".json", request.param)


def _column(rows, key):
    return np.array([row[key] for row in rows], dtype=float)


def test_parallel_training_follows_the_serial_run(training_results):
    mode, results = training_results
    serial, split = results[1]["rows"], results[2]["rows"]
    assert results[2]["ranks"] == 2 and len(split) == len(serial) == 8
    # Data mode sums float32 gradients in another order; mesh mode is float64 with sums over DOFs split in two.
    tolerance = 1e-6 if mode == "data" else 1e-12
    for key in ("train_loss", "val_metric"):
        a, b = _column(serial, key), _column(split, key)
        assert np.abs(a - b).max() <= tolerance * np.abs(a).max(), (key, a, b)
    # Serial and parallel runs take the same solves and the same PRDP decisions; K really moved.
    for key in ("k", "forward_iterations", "backward_iterations"):
        assert [row[key] for row in split] == [row[key] for row in serial], key
    if mode == "mesh-warm":     # warm-started, the tiny inverse improves at every step: PRDP holds k0
        assert {row["k"] for row in serial} == {5}
    else:
        assert len({row["k"] for row in serial}) >= 2
    assert results[2]["k_eps"] == results[1]["k_eps"]


def test_every_rank_uses_the_same_k(training_results):
    _, results = training_results
    first, second = results[2]["ks_by_rank"]
    assert first == second == [row["k"] for row in results[1]["rows"]]


def test_a_resumed_parallel_run_continues_the_uninterrupted_one(training_results):
    _, results = training_results
    full, resumed = results[2]["rows"], results[2]["resumed_rows"]
    for key in ("train_loss", "val_metric"):
        a, b = _column(full, key), _column(resumed, key)
        assert np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), key   # the mesh may be re-partitioned
    assert [row["total_iterations"] for row in full] == [row["total_iterations"] for row in resumed]
    assert results[2]["written_rows"] == resumed   # rank 0 wrote the metrics of the whole run


def test_ranks_that_disagree_are_an_error_that_names_the_values(training_results):
    _, results = training_results
    assert results[2]["check_message"] == ("parallel training went out of step (value: rank 0: 0, rank 1: 1); "
                                           "the ranks must agree on these")
    assert results[1]["check_message"] == ""


TINY_SCENE = tiny_scene(name="tiny-cli-parallel", mesh={"h": 0.25}, data={"train": 8, "validation": 2, "modes": 2},
                        network={"hidden": 8}, optimizer={"lr": None, "epochs": 2, "batch": 4}, prdp=None)


def test_fempdl_run_parallel_data_under_mpirun(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SCENE)
    done = mpirun(2, "-m", "fempdl.app.cli", "run", str(path), "--parallel", "data", "--k", "3", "--no-baseline",
                  "--out", str(tmp_path / "out"))
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.count("scene tiny-cli-parallel") == 1   # rank 0 prints
    assert "on 2 ranks (data)" in done.stdout
    rows = json.loads((tmp_path / "out" / "k3" / "metrics.json").read_text())
    # 8 samples x 2 epochs, one forward and one adjoint solve of K = 3 each, over both ranks.
    assert [row["total_iterations"] for row in rows] == [8 * 2 * 3, 2 * 8 * 2 * 3]


@pytest.mark.parametrize("args, message", [
    (["run", "poisson-inverse", "--parallel", "data"], "has one; use --parallel mesh"),
    (["run", "heat-emulator-2d", "--parallel", "mesh"], "use --parallel data"),
    (["run", "heat-emulator-2d"], "running on 2 ranks needs a mode: `fempdl run heat-emulator-2d --parallel data`"),
    (["compare", "sip-nonlinear"], "scene 'sip-nonlinear': sip scenes train on one process"),
    (["tradeoff", "poisson-inverse"], "`fempdl tradeoff` trains its runs on one process; run it without mpirun "
                                      "(one run on 2 ranks: `fempdl run poisson-inverse --parallel mesh`)"),
    (["run", "no-such-scene"], "fempdl: unknown scene 'no-such-scene'; bundled scenes are"),
    (["run", "poisson-inverse", "--set", "optimizer.epochs=zero"], "fempdl: "),
])
def test_fempdl_refuses_parallel_modes_that_do_not_fit(args, message, tmp_path):
    # A fresh --out: a run left in ./runs by `make run` would be refused first.
    done = mpirun(2, "-m", "fempdl.app.cli", *args, "--out", str(tmp_path / "out"), timeout=120)
    assert done.returncode == 2
    assert message in done.stderr
    if "--parallel" not in args:     # refused before any work: rank 0 says it, once
        assert done.stderr.count("fempdl: ") == 1, done.stderr


def test_the_distributed_mesh_example_recovers_the_serial_source():
    finals = {}
    for ranks in (1, 2):
        done = mpirun(ranks, str(EXAMPLES.parent / "examples" / "distributed_mesh.py"), "--h", "0.05", "--steps", "20")
        assert done.returncode == 0, done.stderr[-3000:]
        last = done.stdout.strip().splitlines()[-1]
        assert last.startswith(f"{ranks} rank(s),"), done.stdout
        finals[ranks] = float(last.rsplit(" ", 1)[1])
    assert finals[2] == pytest.approx(finals[1], rel=1e-8)
    assert finals[1] < 0.2   # 20 steps moved theta towards theta_ref (the start is 0.62 away)


def test_the_data_parallel_example_script_trains_a_scene(tmp_path):
    path = tmp_path / "tiny.toml"
    path.write_text(TINY_SCENE)
    venv_fempdl = Path(sys.executable).parent / "fempdl"
    assert venv_fempdl.exists(), "the example runs the venv's fempdl command"
    done = subprocess.run(["bash", str(EXAMPLES / "mpi_data_parallel.sh"), "2", str(path), "--k", "2",
                           "--no-baseline", "--out", str(tmp_path / "out")],
                          env={**MPI_ENV, "VENV": str(venv_fempdl.parent.parent)},
                          capture_output=True, text=True, timeout=TIMEOUT)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "on 2 ranks (data)" in done.stdout
    assert (tmp_path / "out" / "k2" / "metrics.csv").exists()


def test_ranks_that_disagree_get_an_error_not_a_hang(tmp_path):
    """A distributed layer called with other caps, batches, dtypes or grad modes on the ranks (both layer
    types), a Rollout with other steps, batches, per-step dt or caps (with a schedule, which calls the
    system directly, or without), and PRDP stepped with per-rank metrics, used to hang (one rank in
    KSPSolve, one in VecNorm); ranks at other Constants solved different physics, silently. Now every
    rank raises."""
    out = tmp_path / "guards"
    done = mpirun(2, "guards.py", str(out), timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    caught = [json.loads(Path(f"{out}.rank{r}.json").read_text()) for r in range(2)]
    for rank in caught:
        assert ("called this distributed-mesh SolveLayer differently (caps: [Caps(max_it=5), Caps(max_it=6)], "
                "by rank)") in rank["cap"]
        assert "(batch: [1, 2]; shared (n,) or batched (B, n): [('shared',), ('batched',)], by rank)" in rank["batch"]
        assert "(dtypes: [('float64',), ('float32',)], by rank)" in rank["dtype"]
        assert "(requires_grad: [(True,), (False,)], by rank)" in rank["grad"]
        assert "NonlinearSolveLayer differently (dtypes: [('float64',), ('float32',)], by rank)" in rank["newton_dtype"]
        # The heat form's fixed kappa is one of its Constants too (equal on both ranks).
        assert ("SolveLayer differently (Constants: [(('dt', (0.01,)), ('kappa', (1.0,))), (('dt', (0.02,)), "
                "('kappa', (1.0,)))], by rank)") in rank["constants"]
        assert "called this distributed-mesh Rollout differently (steps: [3, 5]; outputs:" in rank["rollout_steps"]
        assert "Rollout differently (batch: [1, 2]; shared (n,) or batched (B, n)" in rank["rollout_batch"]
        assert "Rollout differently (per-step Constants: [{'dt': [0.01, 0.02, 0.01]}, {'dt': [0.01, 0.02, 0.02]}]" \
            in rank["rollout_dt"]
        assert "Rollout differently (caps: [Caps(max_it=4), Caps(max_it=5)], by rank)" in rank["rollout_caps"]
        assert rank["rollout_agreed"] > 0
        assert "PRDP.step got different metrics on the 2 ranks ([0.5, 1.5])" in rank["prdp"]
        assert rank["k"] == 2 and rank["agreed"] > 0


def test_the_data_parallel_example_trains_as_one_process(tmp_path):
    """examples/data_parallel_loop.py: on two ranks the same metric, K schedule and iterations as on one."""
    example = str(Path(__file__).parent.parent / "examples" / "data_parallel_loop.py")
    results = {}
    for ranks in (1, 2):
        done = mpirun(ranks, example, "--epochs", "12", timeout=240)
        assert done.returncode == 0, done.stderr[-3000:]
        results[ranks] = json.loads(done.stdout.strip().splitlines()[-1])
    one, two = results[1], results[2]
    assert one["ks"] == two["ks"] and one["k"] == two["k"] > 1
    assert one["iterations"] == two["iterations"]
    assert abs(one["metric"] - two["metric"]) <= 1e-9 * one["metric"]


def test_save_fields_on_a_distributed_mesh(tmp_path):
    """--save-fields with --parallel mesh: the ranks write one XDMF file together (it was refused)."""
    path = tmp_path / "inverse.toml"
    path.write_text(tiny_scene("inverse", optimizer={"epochs": 2}))
    out = tmp_path / "out"
    done = mpirun(2, "-m", "fempdl.app.cli", "run", str(path), "--parallel", "mesh", "--k", "3", "--no-baseline",
                  "--no-progress", "--save-fields", "--out", str(out), timeout=180)
    assert done.returncode == 0, done.stderr[-3000:]
    xdmf = (out / "k3" / "fields.xdmf").read_text()
    assert all(f'Name="{label}"' in xdmf for label in ("prediction", "reference", "error"))
    assert (out / "k3" / "fields.h5").exists() and not (out / "k3" / "fields.png").exists()


def test_two_processes_writing_one_xdmf_file_get_an_error(tmp_path):
    """Every rank of a data-parallel loop writing the same file from its own copy of the mesh: the second
    writer gets an error instead of interleaving HDF5 writes."""
    done = mpirun(2, str(SCRIPTS / "one_file.py"), str(tmp_path / "u.xdmf"), timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    outcomes = sorted((tmp_path / f"rank{r}.txt").read_text() for r in range(2))
    assert outcomes[1] == "wrote" and outcomes[0].startswith("another process is writing"), outcomes


def test_observations_on_a_distributed_mesh_equal_the_serial_ones(tmp_path):
    """PointObservation and MassInner on two ranks: the same values and gradients (in DOF-coordinate order)."""
    one, two = on_one_and_two_ranks("observation.py", tmp_path, ".npz", timeout=120).values()
    np.testing.assert_allclose(two["values"], one["values"], rtol=0, atol=1e-13)
    assert abs(float(two["inner"]) - float(one["inner"])) <= 1e-12 * abs(float(one["inner"]))
    np.testing.assert_allclose(two["grad"], one["grad"], rtol=0, atol=1e-12)


def test_health_refinements_on_a_distributed_mesh_equal_the_serial_ones(tmp_path):
    """A garbage capped solve refines PRDP's K on every rank alike, at the serial run's residual ratios."""
    one, two = on_one_and_two_ranks("health.py", tmp_path, ".json", timeout=120).values()
    assert two["ranks"] == 2 and two["same_on_every_rank"]
    assert len(one["newton"]) >= 1 and [e["to"] for e in two["newton"]] == [e["to"] for e in one["newton"]]
    # the forward refines once (8 -> 9) and warns; the adjoint of the same diverging iteration once more
    assert [e["to"] for e in two["linear"]] == [e["to"] for e in one["linear"]] == [9, 10]
    assert one["linear_warned"] and two["linear_warned"]
    for kind in ("newton", "linear"):
        for a, b in zip(one[kind], two[kind]):
            assert abs(a["ratio"] - b["ratio"]) <= 1e-8 * a["ratio"]


def test_a_rollout_on_a_distributed_mesh_equals_the_serial_one(tmp_path):
    """Loss and gradients (along fixed directions) of a 4-step Newton rollout with a varying dt: one node (no
    schedule), by autograd through the steps, under revolve and multistage schedules, and with the lagged LU
    inner solve (GMRES to 1e-12: 1e-8)."""
    results = on_one_and_two_ranks("rollout.py", tmp_path, ".json", timeout=120)
    assert len(results[1]) == 15
    for key, value in results[1].items():
        tol = 1e-8 if key.endswith("lagged") else 1e-12
        assert abs(results[2][key] - value) <= max(tol, 1e-10) * abs(value), key
        plain = results[1][key.split()[0] + " None"]
        assert abs(value - plain) <= tol * abs(plain), key          # every schedule, the same gradient


def test_a_network_in_the_form_on_two_ranks_equals_one_rank_and_ranks_with_other_weights_refuse(tmp_path):
    """The quadrature points are rank-local, the weights' gradient summed over the ranks: with LU the
    solution and both gradients agree to round-off (the condition of this 121-DOF system is ~1e2); ranks
    holding different weights refuse the call together instead of assembling different physics."""
    results = on_one_and_two_ranks("network.py", tmp_path, ".npz")
    for key in ("u", "grad_f", "grad_theta"):
        a, b = results[1][key], results[2][key]
        assert a.shape == b.shape and np.abs(a - b).max() <= 1e-12 * np.abs(a).max(), key
    path = tmp_path / "differ.npz"
    done = mpirun(2, "network.py", "differ", str(path))
    assert done.returncode == 0, done.stderr[-3000:]
    assert "every rank must call it with the same network weights" in str(np.load(path)["refused"])
