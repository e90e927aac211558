#!/usr/bin/env bash
# Sets up everything fempdl needs on Debian bookworm, idempotently:
#   1. DOLFINx 0.5 / PETSc / mpi4py / gmsh from Debian (for /usr/bin/python3),
#   2. a venv made from /usr/bin/python3 with --system-site-packages,
#   3. torch (CPU build) and fempdl itself in editable mode with its test extra.
# Usage: tools/setup_env.sh [VENV_DIR]   (default: .venv)
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-.venv}"
apt_pkgs="python3-dolfinx python3-petsc4py python3-mpi4py python3-gmsh python3-matplotlib python3-venv"

if ! /usr/bin/python3 -c "import dolfinx, petsc4py, mpi4py, gmsh, matplotlib" >/dev/null 2>&1 \
   || ! /usr/bin/python3 -c "import ensurepip" >/dev/null 2>&1; then
    sudo=""
    [ "$(id -u)" -ne 0 ] && sudo="sudo"
    echo "[setup] installing Debian packages: $apt_pkgs"
    $sudo apt-get update -q
    DEBIAN_FRONTEND=noninteractive $sudo apt-get install -y -q $apt_pkgs
fi

if [ ! -x "$venv/bin/python" ]; then
    echo "[setup] creating $venv from /usr/bin/python3 (with system site-packages)"
    /usr/bin/python3 -m venv --system-site-packages "$venv"
fi

stamp="$venv/.fempdl-installed"
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] \
   || ! "$venv/bin/python" -c "import torch, fempdl, pytest, tensorboard" >/dev/null 2>&1 \
   || [ ! -x "$venv/bin/ruff" ]; then
    echo "[setup] installing torch and fempdl into $venv"
    # torch==2.13.0 is the CPU wheel available locally; an unpinned torch would pull a CUDA build.
    "$venv/bin/python" -m pip install -q --disable-pip-version-check torch==2.13.0
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -e ".[test,tensorboard]"
    touch "$stamp"
fi
