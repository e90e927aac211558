"""Under mpirun -n 2: fields of a distributed mesh round-trip and reach XDMF with their ghosts (tests/mpi/fields.py)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from fempdl.core import _dolfinx

MPI_ENV = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1", "OMP_NUM_THREADS": "1"}


def test_distributed_fields(tmp_path):
    script = Path(__file__).parent / "mpi" / "fields.py"
    done = subprocess.run([*_dolfinx.mpi_launcher(), "-n", "2", sys.executable, str(script), str(tmp_path)],
                          env=MPI_ENV, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads((tmp_path / "result.json").read_text())
    errors = result.pop("errors")
    assert {k: v for k, v in errors.items() if k.endswith("round_trip")} == {
        f"{label}/{name}/round_trip": 0.0
        for label, names in (("poisson", ("None", "f")), ("stokes", ("None", "u", "p"))) for name in names}
    assert result["ghosts"] > 0 and errors["poisson/p1_nodes_with_ghosts"] < 1e-13
    assert result["nodes"] == result["vertices"]          # one XDMF node per mesh vertex, gathered from both ranks
    assert (tmp_path / "poisson.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
