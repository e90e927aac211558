"""The version shim: what it reports about the stack, and the calls that differ between stacks.

The same assertions hold on Debian's DOLFINx 0.5.2 / PETSc 3.18 and on
DOLFINx 0.11 / PETSc 3.25 from PyPI; where a capability differs, the test asks
the shim which stack it runs on.
"""
from __future__ import annotations

import os

from mpi4py import MPI
import dolfinx
import pytest
from petsc4py import PETSc

from fempdl import forms, mesh
from fempdl.core import _dolfinx, matrices
from fempdl.ksp_adjoint import KSPOptions

COMM = MPI.COMM_WORLD


def test_the_shim_names_the_stack_it_runs_on():
    assert _dolfinx.DOLFINX_VERSION == tuple(int(p) for p in dolfinx.__version__.split(".")[:2])
    assert _dolfinx.PETSC_VERSION == tuple(PETSc.Sys.getVersion())
    if _dolfinx.STACK == "debian":
        assert _dolfinx.DOLFINX_VERSION == (0, 5) and _dolfinx.PETSC_VERSION[:2] == (3, 18)
    else:
        assert _dolfinx.STACK == "current" and _dolfinx.DOLFINX_VERSION >= (0, 9)


def test_the_mpi_launcher_belongs_to_the_mpi_mpi4py_loaded():
    launcher = _dolfinx.mpi_launcher()
    assert os.access(launcher[0], os.X_OK)
    open_mpi = "Open MPI" in MPI.Get_library_version()
    assert (launcher[1:] == ["--oversubscribe"]) == open_mpi


@pytest.fixture(scope="module")
def poisson():
    return forms.poisson.problem(mesh.load("lshape", COMM, h=0.1), controls=("f",))


@pytest.fixture(scope="module")
def matrix(poisson):
    A = matrices.create_matrix(poisson.a_form)
    matrices.assemble_matrix_into(A, poisson.a_form, poisson.bcs)
    yield A
    A.destroy()


def test_vectors_have_the_test_space_layout_with_ghosts(poisson, matrix):
    b = _dolfinx.create_vector(poisson.L_form)
    imap = poisson.V.dofmap.index_map
    assert b.getLocalSize() == imap.size_local == matrix.getLocalSize()[0]
    assert b.getSize() == imap.size_global
    with b.localForm() as loc:
        assert loc.getSize() == imap.size_local + imap.num_ghosts
    _dolfinx.assemble_vector_into(b, poisson.L_form, poisson.a_form, poisson.bcs)
    assert b.norm() > 0.0       # f = 1 by default: a nonzero load
    b.destroy()


def test_cell_dofs_and_cell_diameters_have_one_row_per_cell(poisson):
    msh = poisson.V.mesh
    n_local = msh.topology.index_map(msh.topology.dim).size_local
    n_ghost = msh.topology.index_map(msh.topology.dim).num_ghosts
    assert _dolfinx.cell_dofs(poisson.V).shape == (n_local + n_ghost, 3)      # P1 triangles
    h = _dolfinx.cell_diameters(msh)
    assert h.shape == (n_local,) and 0.02 < h.min() <= h.max() < 0.3        # mesh size 0.1


def test_the_schur_preset_uses_hypre_only_where_petsc_has_it():
    inner = KSPOptions.preset("schur").petsc_options["fieldsplit_p_lsc_pc_type"]
    assert inner == ("hypre" if PETSc.Sys.hasExternalPackage("hypre") else "lu")


@pytest.mark.parametrize("pc_type", ["fieldsplit", "hypre", "sor"])
def test_preconditioners_without_a_true_transpose_get_the_assembled_adjoint(pc_type):
    # Measured by benchmarks/bench_pc_transpose.py on both stacks.
    assert KSPOptions(ksp_type="gmres", pc_type=pc_type, max_it=5).assembled_adjoint
    assert not KSPOptions(ksp_type="gmres", pc_type="ilu", max_it=5).assembled_adjoint
