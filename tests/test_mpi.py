"""Layers on a mesh distributed over MPI ranks give the serial numbers.

The scripts in ``tests/mpi/`` run under ``mpirun -n 2`` in a subprocess (with
a timeout, so a hang fails the test instead of stalling the suite) and write
their results from rank 0; the comparison is in DOF-coordinate order.
"""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

SCRIPTS = Path(__file__).parent / "mpi"
TIMEOUT = 300


def mpirun(ranks: int, script: str, *args: str, timeout: float = TIMEOUT) -> subprocess.CompletedProcess:
    launcher = shutil.which("mpirun")
    assert launcher is not None, "mpirun is not installed (Debian: openmpi-bin, pulled in by python3-mpi4py)"
    env = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1",
           "OMP_NUM_THREADS": "1"}
    command = [launcher, "--oversubscribe", "-n", str(ranks), sys.executable, str(SCRIPTS / script), *args]
    return subprocess.run(command, env=env, capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def layer_results(tmp_path_factory):
    out = tmp_path_factory.mktemp("mpi")
    results = {}
    for ranks in (1, 2):
        path = out / f"ranks{ranks}.npz"
        done = mpirun(ranks, "layer_gradients.py", str(path))
        assert done.returncode == 0, done.stderr[-3000:]
        results[ranks] = dict(np.load(path))
    return results


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


def test_an_error_on_one_rank_ends_the_job_instead_of_hanging():
    done = mpirun(2, "injected_failure.py", timeout=60)  # a hang raises TimeoutExpired
    assert done.returncode != 0
    assert "[rank 1] RuntimeError: injected failure on rank 1" in done.stderr
    assert "[rank 1] aborting all 2 ranks" in done.stderr
    assert "unreachable" not in done.stdout
