#!/usr/bin/env bash
# Data-parallel training of a scene under mpirun: every rank builds the whole
# problem on its own (mesh on COMM_SELF), takes 1/P of every batch and of the
# validation samples; gradients are summed over the ranks before each step,
# every rank takes the same PRDP decisions (checked after every epoch), and
# rank 0 writes metrics.csv/json and the checkpoints. With the same seed the
# losses equal the serial run's to float32 rounding.
#
#   bash tools/mpi_data_parallel.sh                      # 2 ranks, burgers-emulator, PRDP + baseline
#   bash tools/mpi_data_parallel.sh 2 heat-emulator-2d --k 8 --no-baseline
#   bash tools/mpi_data_parallel.sh 2 burgers-emulator --resume   # continue an interrupted run
#
# A resumed run needs the same number of ranks. As root, Open MPI also wants
# OMPI_ALLOW_RUN_AS_ROOT=1 OMPI_ALLOW_RUN_AS_ROOT_CONFIRM=1 in the environment.
# VENV=.venv-pypi runs the PyPI stack (its MPICH mpiexec); the default is .venv.
set -euo pipefail
cd "$(dirname "$0")/.."
venv="${VENV:-.venv}"
ranks=${1:-2}
scene=${2:-burgers-emulator}
shift $(( $# < 2 ? $# : 2 ))
# The launcher of the MPI the venv's mpi4py uses (Open MPI's mpirun or MPICH's mpiexec).
read -r -a launcher < <("$venv/bin/python" -c "from fempdl.core import _dolfinx; print(*_dolfinx.mpi_launcher())")
exec "${launcher[@]}" -n "$ranks" "$venv/bin/fempdl" run "$scene" --parallel data --no-progress "$@"
