#!/usr/bin/env bash
# Sets up the second supported stack, everything from PyPI, idempotently:
#   1. a venv made from the machine's Python 3.12 (python3.12 on PATH, or pyenv's),
#   2. DOLFINx 0.11 with PETSc 3.25 (dolfinx-solver-real: also brings mpi4py and
#      MPICH, whose mpiexec lands in the venv), gmsh and torch,
#   3. fempdl itself in editable mode with its test extra (numpy 2, scipy, matplotlib).
# torch==2.13.0 on Python 3.12 is PyPI's CUDA build (about 5 GB with its CUDA
# libraries); it runs on the CPU.
# Usage: scripts/setup_env_pypi.sh [VENV_DIR]   (default: .venv-pypi)
#        PYTHON312=/path/to/python3.12 scripts/setup_env_pypi.sh   to choose the interpreter
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
if [ ! -f "$stamp" ] || [ pyproject.toml -nt "$stamp" ] || [ "$0" -nt "$stamp" ] \
   || ! "$venv/bin/python" -c "from mpi4py import MPI; import dolfinx, gmsh, torch, fempdl, pytest, tensorboard" >/dev/null 2>&1; then
    echo "[setup] installing ${pkgs[*]} and fempdl into $venv"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check "${pkgs[@]}"
    "$venv/bin/python" -m pip install -q --disable-pip-version-check -e ".[test,tensorboard]"
    touch "$stamp"
fi
