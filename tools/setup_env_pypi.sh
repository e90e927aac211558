#!/usr/bin/env bash
# Sets up the second supported stack, everything from PyPI, idempotently:
#   1. a venv made from the machine's Python 3.12 (python3.12 on PATH, or pyenv's),
#   2. DOLFINx 0.11 with PETSc 3.25 (dolfinx-solver-real: also brings mpi4py and
#      MPICH, whose mpiexec lands in the venv), gmsh and torch,
#   3. fempdl itself in editable mode with its test extra (numpy 2, scipy, matplotlib).
# torch==2.13.0 on Python 3.12 is PyPI's CUDA build (5.3 GiB with its CUDA
# libraries); it runs on the CPU.
# Usage: tools/setup_env_pypi.sh [VENV_DIR]   (default: .venv-pypi)
#        PYTHON312=/path/to/python3.12 tools/setup_env_pypi.sh   to choose the interpreter
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${1:-.venv-pypi}"
pkgs=("dolfinx-solver-real==0.11.*" "gmsh==4.15.*" "torch==2.13.0")

is_python312() {
    [ -n "$1" ] && "$1" -c "import sys; assert sys.version_info[:2] == (3, 12)" >/dev/null 2>&1
}

# The first of $PYTHON312, python3.12 on PATH (pyenv's shim fails unless a 3.12
# is selected) and pyenv's installed 3.12 versions that runs and is 3.12.
find_python312() {
    local root="${PYENV_ROOT:-$HOME/.pyenv}" candidate
    for candidate in "${PYTHON312:-}" "$(command -v python3.12 || true)" "$root"/versions/3.12*/bin/python3.12; do
        if is_python312 "$candidate"; then echo "$candidate"; return; fi
    done
}

if [ ! -x "$venv/bin/python" ]; then
    python312="$(find_python312)"
    if [ -z "$python312" ]; then
        echo "[setup] no Python 3.12 found (looked for \$PYTHON312, python3.12 on PATH, pyenv's versions);" \
             "install one (e.g. pyenv install 3.12) or set PYTHON312=/path/to/python3.12" >&2
        exit 1
    fi
    echo "[setup] creating $venv from $python312"
    "$python312" -m venv "$venv"
fi

stamp="$venv/.fempdl-installed"
# PyPI's torch for Python 3.12 is the CUDA build: a fresh install grows the disk's
# use by about 6.3 GiB at its peak (5.3 GiB stay), so a nearly full disk fails
# midway with pip's "No space left on device". Say so before starting instead.
need_gb=8
require_free_space() {
    local dir free_gb
    for dir in "$venv" "${TMPDIR:-/tmp}"; do
        free_gb=$(( $(df -Pk "$dir" | awk 'NR==2 {print $4}') / 1048576 ))
        if [ "$free_gb" -lt "$need_gb" ]; then
            echo "[setup] $dir has ${free_gb} GiB free; installing torch's CUDA build for Python 3.12" \
                 "needs ${need_gb} GiB while pip unpacks it. Free some space and rerun." >&2
            exit 1
        fi
    done
}

if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ "$0" -nt "$stamp" ] \
   || ! "$venv/bin/python" -c "from mpi4py import MPI; import dolfinx, gmsh, torch, fempdl, pytest, tensorboard" >/dev/null 2>&1; then
    "$venv/bin/python" -c "import torch" >/dev/null 2>&1 || require_free_space
    echo "[setup] installing ${pkgs[*]} and fempdl into $venv"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check "${pkgs[@]}"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -e ".[test,tensorboard]"
    touch "$stamp"
fi
