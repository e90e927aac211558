"""Helpers shared by the benchmark scripts: the machine record, JSON output, list options."""
from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

# Before anything loads an OpenMP runtime: spinning threads would stall the other
# process of a paired measurement (fempdl's __init__ sets the same default).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

from mpi4py import MPI  # before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads
import dolfinx
import numpy as np
import petsc4py
import torch
from petsc4py import PETSc

import fempdl
from fempdl.app.runs.training import write_atomically
from fempdl.core import _dolfinx


def machine_info() -> dict:
    meminfo = {}
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                key, value = line.split(":", 1)
                if key in ("MemTotal", "MemAvailable"):
                    meminfo[key] = int(value.split()[0]) / 1024.0 / 1024.0
    except OSError:
        pass
    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "memory_total_gib": meminfo.get("MemTotal"),
        "memory_available_gib_at_start": meminfo.get("MemAvailable"),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_num_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "runtime default"),
        "load_average_1_5_15_min_at_start": list(os.getloadavg()),
        "stack": _dolfinx.STACK,
        "dolfinx": dolfinx.__version__,
        "petsc": ".".join(map(str, PETSc.Sys.getVersion())),
        "petsc4py": petsc4py.__version__,
        "numpy": np.__version__,
        "fempdl": fempdl.__version__,
        "mpi_ranks": MPI.COMM_WORLD.size,
    }


def write_json_atomically(data: dict, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda p: p.write_text(json.dumps(data, indent=2)))


def run_mpi_worker(script, ranks: int, worker_args: list, out: Path) -> dict:
    """Run ``script`` with ``worker_args`` under ``mpirun -n ranks`` (root allowed) and read the
    JSON its rank 0 wrote to ``out``; a failed job raises with the end of its stderr."""
    command = [*_dolfinx.mpi_launcher(), "-n", str(ranks), sys.executable, str(script), *map(str, worker_args)]
    env = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads(Path(out).read_text())


def comma_list(kind):
    def parse(text: str) -> list:
        return [kind(item) for item in text.split(",") if item]
    return parse


def apply_defaults(parser, args, defaults: dict, mesh_sizes, solvers) -> None:
    """Fill the options left unset from ``defaults`` and check --sizes, --solvers and --ks."""
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    for size in args.sizes:
        if size not in mesh_sizes:
            parser.error(f"--sizes: unknown size {size!r}; choose from {sorted(mesh_sizes)}")
    for name in args.solvers:
        if name not in solvers:
            parser.error(f"--solvers: unknown solver {name!r}; choose from {sorted(solvers)}")
    if not args.ks or min(args.ks) < 1:
        parser.error(f"--ks must be integers >= 1, got {args.ks}")
