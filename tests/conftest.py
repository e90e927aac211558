"""Session fixtures: meshes and problems. Shared helpers and constants live in helpers.py."""
from __future__ import annotations

from mpi4py import MPI
import pytest
import torch

from fempdl import mesh

from helpers import FORM_CONTROLS, build

# The tests' tensors are small: one thread avoids thread start-up costs per op
# and oversubscribing a shared 2-core machine (numbers do not depend on it).
torch.set_num_threads(1)


@pytest.fixture(scope="session")
def coarse_lshape():
    """About 100 P1 DOFs: small enough for full float64 gradcheck."""
    return mesh.load("lshape", MPI.COMM_WORLD, h=0.25)


@pytest.fixture(scope="session")
def lshape():
    """The bundled L-shape (about 1.5k P1 DOFs)."""
    return mesh.load("lshape", MPI.COMM_WORLD)


@pytest.fixture(scope="session")
def coarse_problems(coarse_lshape):
    return {form: build(form, coarse_lshape) for form in FORM_CONTROLS}
