"""PETSc conventions: DOLFINx-style option dicts and a user's options prefix.

A prefix's command-line options are simulated by putting them into PETSc's
options database before the solver is created (what PETSc does with the
command line and PETSC_OPTIONS); one test runs a layer in a subprocess with
PETSC_OPTIONS and reads PETSc's own -ksp_view output.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from petsc4py import PETSc

from fempdl import forms, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import CappedSolver, KSPOptions
from fempdl.solve.newton_options import NewtonOptions


@pytest.fixture(scope="module")
def laplacian():
    """The 1D Dirichlet Laplacian tridiag(-1, 2, -1) on 50 unknowns (SPD)."""
    n = 50
    A = PETSc.Mat().createAIJ((n, n), nnz=3, comm=PETSc.COMM_SELF)
    for i in range(n):
        A.setValue(i, i, 2.0)
        if i:
            A.setValue(i, i - 1, -1.0)
            A.setValue(i - 1, i, -1.0)
    A.assemble()
    yield A
    A.destroy()


def test_dolfinx_style_dict_maps_onto_fields():
    opts = KSPOptions.from_petsc_options({
        "ksp_type": "gmres", "pc_type": "jacobi", "ksp_rtol": "1e-8", "ksp_atol": 1e-30, "ksp_max_it": "40",
        "ksp_divtol": 1e6, "-ksp_gmres_restart": 12, "ksp_gmres_modifiedgramschmidt": None,
        "pc_jacobi_type": "rowmax"}, on_failure="warn")
    assert opts == KSPOptions(ksp_type="gmres", pc_type="jacobi", rtol=1e-8, atol=1e-30, max_it=40, divtol=1e6,
                              gmres_restart=12, on_failure="warn",
                              petsc_options={"ksp_gmres_modifiedgramschmidt": None, "pc_jacobi_type": "rowmax"})
    # without ksp_max_it the solve runs to rtol, as in PETSc
    direct = KSPOptions.from_petsc_options({"ksp_type": "preonly", "pc_type": "lu",
                                            "pc_factor_mat_solver_type": "mumps"})
    assert direct.max_it is None and direct.direct
    assert dict(direct.petsc_options) == {"pc_factor_mat_solver_type": "mumps"}
    assert not KSPOptions.from_petsc_options({"ksp_type": "cg", "pc_type": "jacobi"}).capped
    assert KSPOptions.from_petsc_options({}) == KSPOptions(ksp_type="gmres", pc_type="bjacobi", max_it=None)


def test_dict_errors_name_the_key():
    with pytest.raises(ValueError, match=r"options\['ksp_max_it'\] must be a number, got 'ten'"):
        KSPOptions.from_petsc_options({"ksp_type": "cg", "ksp_max_it": "ten"})
    with pytest.raises(ValueError, match=r"options\['ksp_max_it'\] must be a whole number, got 2.5"):
        KSPOptions.from_petsc_options({"ksp_max_it": 2.5})
    with pytest.raises(TypeError, match=r"options\['pc_type'\] must be a type name \(str\), got 3"):
        KSPOptions.from_petsc_options({"pc_type": 3})
    with pytest.raises(ValueError, match=r"options\['ksp_rtol'\] and the keyword rtol= both set rtol"):
        KSPOptions.from_petsc_options({"ksp_rtol": 1e-6}, rtol=1e-8)
    with pytest.raises(ValueError, match=r"petsc_options\['ksp_initial_guess_nonzero'\] is not supported"):
        KSPOptions.from_petsc_options({"ksp_initial_guess_nonzero": True})
    with pytest.raises(ValueError, match=r"petsc_options\['ksp_rtol'\] conflicts with a KSPOptions field; set "
                                         r"rtol instead, or .* KSPOptions.from_petsc_options"):
        KSPOptions(petsc_options={"ksp_rtol": 1e-6})


def test_reserved_keys_are_refused_in_any_letter_case(coarse_lshape):
    """PETSc reads KSP_MAX_IT as ksp_max_it: it ran 200 iterations under a layer that reported max_it=5,
    and Ksp_Type: preonly turned capped CG into one Jacobi application, both silently."""
    for key, value in (("KSP_MAX_IT", 200), ("Ksp_Type", "preonly"), ("PC_TYPE", "none"), ("Ksp_Rtol", 1e-3)):
        with pytest.raises(ValueError, match=rf"petsc_options\['{key}'\] conflicts with a KSPOptions field"):
            KSPOptions.preset("cg", max_it=5, petsc_options={key: value})
    with pytest.raises(ValueError, match=r"petsc_options\['KSP_Initial_Guess_Nonzero'\] is not supported"):
        KSPOptions(petsc_options={"KSP_Initial_Guess_Nonzero": True})
    with pytest.raises(ValueError, match=r"\['ksp_view'\] and petsc_options\['KSP_VIEW'\] name the same PETSc option"):
        KSPOptions(petsc_options={"ksp_view": None, "KSP_VIEW": None})
    # Other keys keep working, stored in lower case (the name PETSc matches anyway).
    assert dict(KSPOptions.preset("jacobi", max_it=5, petsc_options={"KSP_Richardson_Scale": 0.5}).petsc_options) \
        == {"ksp_richardson_scale": 0.5}
    # DOLFINx-style dicts map reserved keys in any case onto fields, once.
    assert KSPOptions.from_petsc_options({"KSP_TYPE": "cg", "Pc_Type": "jacobi", "KSP_MAX_IT": "5"}) \
        == KSPOptions(ksp_type="cg", pc_type="jacobi", max_it=5)
    with pytest.raises(ValueError, match=r"options\['ksp_max_it'\] and options\['KSP_MAX_IT'\] both set max_it"):
        KSPOptions.from_petsc_options({"ksp_max_it": 5, "KSP_MAX_IT": 200})
    # A Newton layer's inner solve is a KSPOptions: the same checks.
    with pytest.raises(ValueError, match=r"petsc_options\['KSP_MAX_IT'\] conflicts"):
        NewtonOptions(ksp=KSPOptions.preset("jacobi", max_it=3, petsc_options={"KSP_MAX_IT": 200}))
    # The cap holds: a capped layer runs exactly max_it iterations.
    layer = SolveLayer(forms.poisson.problem(coarse_lshape, controls=("f",)),
                       KSPOptions.preset("jacobi", max_it=5, petsc_options={"KSP_Richardson_Scale": 0.9}))
    layer(f=torch.ones(layer.problem.control_size("f"), dtype=torch.float64))
    assert layer.stats.forward_iterations == 5


def test_dict_options_solve_to_rtol(laplacian):
    opts = KSPOptions.from_petsc_options({"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": 1e-12})
    b, x = laplacian.createVecLeft(), laplacian.createVecRight()
    b.setArray(np.linspace(-1.0, 1.0, 50))
    with CappedSolver(laplacian, opts) as solver:
        stats = solver.solve(b, x)
    indptr, indices, data = laplacian.getValuesCSR()
    exact = spla.spsolve(sp.csr_matrix((data, indices, indptr)).tocsc(), b.getArray())
    assert stats.ok and not stats.capped and stats.iterations <= 25      # CG: at most n/2 on this spectrum
    np.testing.assert_allclose(x.getArray(), exact, rtol=0, atol=1e-10 * np.abs(exact).max())


def test_petsc_default_types_solve_and_transpose(laplacian):
    opts = KSPOptions.from_petsc_options({"ksp_rtol": "1e-12"})
    b, x, y = laplacian.createVecLeft(), laplacian.createVecRight(), laplacian.createVecRight()
    b.setArray(np.cos(np.arange(50.0)))
    with CappedSolver(laplacian, opts) as solver:
        assert solver.solve(b, x).ok and solver.solve_transpose(b, y).ok
    indptr, indices, data = laplacian.getValuesCSR()
    exact = spla.spsolve(sp.csr_matrix((data, indices, indptr)).tocsc(), b.getArray())
    np.testing.assert_allclose(x.getArray(), exact, rtol=0, atol=1e-9 * np.abs(exact).max())
    np.testing.assert_allclose(y.getArray(), exact, rtol=0, atol=1e-9 * np.abs(exact).max())   # A symmetric


def test_user_prefix_reads_the_database_and_keeps_user_options(laplacian):
    db = PETSc.Options()
    db["tp_ksp_gmres_restart"] = 7          # as given on a command line
    db["tp_pc_type"] = "none"
    db["tp_pc_jacobi_type"] = "rowmax"      # also in petsc_options below: the database's value wins
    try:
        opts = KSPOptions(ksp_type="gmres", pc_type="jacobi", gmres_restart=30, max_it=5, options_prefix="tp_",
                          petsc_options={"pc_jacobi_type": "rowsum", "ksp_gmres_modifiedgramschmidt": None})
        first = CappedSolver(laplacian, opts)
        second = CappedSolver(laplacian, opts)
        assert first.ksp.getOptionsPrefix() == "tp_"
        assert first.ksp.getPC().getType() == "none"                # the command line overrides pc_type
        assert db.getString("tp_pc_jacobi_type") == "rowmax"
        assert db.hasName("tp_ksp_gmres_modifiedgramschmidt")
        first.destroy()
        assert db.hasName("tp_ksp_gmres_modifiedgramschmidt")      # the second solver still uses it
        second.destroy()
        assert not db.hasName("tp_ksp_gmres_modifiedgramschmidt")
        assert db.getInt("tp_ksp_gmres_restart") == 7 and db.getString("tp_pc_jacobi_type") == "rowmax"
    finally:
        db.delValue("tp_ksp_gmres_restart")
        db.delValue("tp_pc_jacobi_type")
        db.delValue("tp_pc_type")


def test_private_prefix_still_removes_its_options(laplacian):
    opts = KSPOptions(ksp_type="gmres", pc_type="jacobi", max_it=5,
                      petsc_options={"ksp_gmres_modifiedgramschmidt": None})
    solver = CappedSolver(laplacian, opts)
    prefix = solver.ksp.getOptionsPrefix()
    assert prefix.startswith("fempdl_ksp") and PETSc.Options().hasName(prefix + "ksp_gmres_modifiedgramschmidt")
    solver.destroy()
    assert not any(key.startswith(prefix) for key in PETSc.Options().getAll())


def test_prefix_is_validated():
    for bad in ("-my_", "9x_", "my prefix", "fempdl_mine_"):
        with pytest.raises(ValueError, match=r"options_prefix must be letters, digits and underscores .* got "
                                             + repr(bad)):
            KSPOptions(options_prefix=bad)


def test_prefixed_layer_runs_on_petsc_and_shows_command_line_options(tmp_path):
    script = tmp_path / "layer.py"
    script.write_text(
        "import torch\n"
        "from fempdl import forms, mesh\n"
        "from fempdl.ksp_adjoint import KSPOptions\n"
        "from fempdl.bridge_torch import SolveLayer\n"
        "prob = forms.poisson.problem(mesh.load('lshape', h=0.3), controls=('f',))\n"
        "layer = SolveLayer(prob, KSPOptions(max_it=3, options_prefix='my_'))\n"
        "layer(f=torch.ones(2, prob.control_size('f'), dtype=torch.float64))\n"
        "print('engines', layer.stats.solves_by_engine)\n")
    env = {**os.environ, "PETSC_OPTIONS": "-my_ksp_view -my_ksp_converged_reason", "OMP_WAIT_POLICY": "PASSIVE"}
    out = subprocess.run([sys.executable, str(script)], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    # Richardson batches go to the batched engine unless a prefix asks for PETSc's KSP
    assert "engines {'petsc': 2}" in out.stdout
    assert out.stdout.count("KSP Object: (my_) 1 MPI process") == 2
    assert out.stdout.count("Linear my_ solve converged due to CONVERGED_ITS iterations 3") == 2


def test_prefixed_layer_gives_the_same_solution():
    prob = forms.poisson.problem(mesh.load("lshape", h=0.3), controls=("f",))
    f = torch.linspace(0.0, 1.0, prob.control_size("f"), dtype=torch.float64).repeat(3, 1)
    plain = SolveLayer(prob, KSPOptions(max_it=4))(f=f)
    prefixed = SolveLayer(prob, KSPOptions(max_it=4, options_prefix="same_"))
    u = prefixed(f=f)
    assert prefixed.stats.solves_by_engine == {"petsc": 3}
    torch.testing.assert_close(u, plain, rtol=0, atol=1e-14)
