"""Shared meshes, problems and the solver x form configurations the tests run over."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from mpi4py import MPI
import dolfinx.fem

from fempdl import forms, mesh
from fempdl.ksp_adjoint import KSPOptions

# The tests' tensors are small: one thread avoids thread start-up costs per op
# and oversubscribing a shared 2-core machine (numbers do not depend on it).
torch.set_num_threads(1)

# Converged solvers: gradients must be exact (gradcheck, Taylor test).
CONVERGED = {
    "lu": KSPOptions.preset("lu"),
    "cg": KSPOptions.preset("cg", rtol=1e-13),
}
# Capped solvers: exact iteration counts; implicit gradients exact for Jacobi (RHS
# controls), approximate for Krylov methods.
CAPPED = {
    "jacobi": lambda k: KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=k),
    "gmres": lambda k: KSPOptions.preset("gmres", max_it=k, gmres_restart=5),
    "cg": lambda k: KSPOptions.preset("cg", max_it=k),
}
# Every control of every form module, and the variants that change which
# controls enter the matrix or the right-hand side (theta < 1 puts kappa into L;
# theta = 0 makes kappa an affine RHS control on its own DG0 space) or the
# sizes of the spaces (P2 solution, DG0 coefficient).
FORM_CONTROLS = {
    "poisson": ("f", "kappa"),
    "poisson-p2-dg0": ("f", "kappa"),
    "heat": ("u0", "f", "kappa"),
    "heat-cn": ("u0", "f", "kappa"),
    "heat-explicit-dg0": ("u0", "f", "kappa"),
}
FORM_VARIANTS = {
    "poisson": {},
    "poisson-p2-dg0": {"degree": 2, "kappa_space": "DG0"},
    "heat": {},
    "heat-cn": {"theta": 0.5},
    "heat-explicit-dg0": {"theta": 0.0, "kappa_space": "DG0"},
}
FORM_CONTROL_PAIRS = [(form, c) for form, cs in FORM_CONTROLS.items() for c in cs]


def smooth(x):
    return 1.0 + 0.5 * np.sin(np.pi * x[0]) * np.cos(np.pi * x[1])


def build(form: str, msh, controls=None, **kw):
    """A problem of the named form variant with every control (or the given ones)."""
    controls = FORM_CONTROLS[form] if controls is None else controls
    kw = {**FORM_VARIANTS[form], **kw}
    if form.startswith("poisson"):
        return forms.poisson.problem(msh, controls=controls, kappa=smooth, **kw)
    return forms.heat.problem(msh, controls=controls, dt=0.05, kappa=smooth,
                              u0=lambda x: np.sin(np.pi * x[0]), **kw)


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


def control_values(prob, name: str, batch: int, seed: int = 0) -> torch.Tensor:
    """A positive, smooth-plus-noise control batch (kappa stays well away from 0)."""
    gen = torch.Generator().manual_seed(seed)
    n = prob.control_size(name)
    base = torch.as_tensor(prob.interpolate(smooth, name))
    noise = 0.2 * torch.rand(batch, n, generator=gen, dtype=torch.float64)
    return (base + noise) if name == "kappa" else (base - 1.0 + noise)


def integral(form, comm) -> float:
    """A compiled functional assembled and summed over ``comm``."""
    return comm.allreduce(dolfinx.fem.assemble_scalar(form), op=MPI.SUM)
