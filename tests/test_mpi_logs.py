"""Under mpirun -n 2 (stderr is a pipe, not a terminal): one epoch line per epoch, from rank 0 only."""
from __future__ import annotations

import os
import re
import subprocess
import sys

from fempdl.core import _dolfinx

from helpers import CLI_TINY, tiny_scene

MPI_ENV = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1", "OMP_NUM_THREADS": "1"}


def test_epoch_lines_under_mpirun(tmp_path):
    scene = tmp_path / "tiny.toml"
    scene.write_text(tiny_scene("emulator", CLI_TINY))
    done = subprocess.run([*_dolfinx.mpi_launcher(), "-n", "2", sys.executable, "-m", "fempdl.app.cli", "run",
                           str(scene), "--k", "2", "--no-baseline", "--parallel", "data",
                           "--out", str(tmp_path / "out"), "--set", "optimizer.epochs=3"],
                          env=MPI_ENV, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    epochs = re.findall(r"^fempdl: k2: epoch (\d)/3 loss \S+ val \S+ K 2 iterations (\d+) wall", done.stderr, re.M)
    # 16 training samples spread over the ranks, counted over both: 16 * K forward iterations per epoch, and backward
    assert epochs == [("1", str(16 * 2 * 2)), ("2", str(2 * 16 * 2 * 2)), ("3", str(3 * 16 * 2 * 2))]
    assert len(re.findall(r"^fempdl: K_eps = \d+ ", done.stderr, re.M)) == 1
