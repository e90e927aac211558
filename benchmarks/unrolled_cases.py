"""The workload bench_unrolled.py measures: the Poisson problem, its variants of SolveLayer, the timed call
and the checks that the variants agree.

:data:`VARIANTS` names each layer (diff mode, engine, checkpointed or not); :func:`make_layer` builds one
capped at K, :func:`layer_call` runs ``u = layer(f=F); (u * W).sum().backward()`` and
:func:`check_outputs` compares the variants' outputs and gradients. Used both by the benchmark and
by its memory subprocesses (``unrolled_memory.py``).
"""
from __future__ import annotations

import time

from mpi4py import MPI  # noqa: F401  (before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads)
import numpy as np
import torch

import fempdl.core.mesh
import fempdl.forms
from fempdl.bridge_torch import SolveLayer
from fempdl.iterative import unrolled
from fempdl.ksp_adjoint import KSPOptions

MESH_SIZES = {"small": 0.03, "large": 0.0073}   # h -> about 4k and 66k P1 DOFs (fempdl.core.meshgen)
SOLVERS = ("jacobi", "cg")                      # Richardson+Jacobi, CG+Jacobi
UNROLLED_METHOD = {"jacobi": "jacobi", "cg": "cg"}  # their fempdl.iterative.unrolled method names
AGREEMENT_TOL = 1e-12           # relative; forward always, gradients for Jacobi
ROUND_OFF = 1e-15               # relative perturbation of F that measures the output's round-off sensitivity
SENSITIVITY_FACTOR = 10         # forward tolerance: max(AGREEMENT_TOL, this * that sensitivity)
# Variants: (diff, engine, checkpointed). "implicit" and "unrolled" use the default engine.
VARIANTS = {
    "implicit": ("implicit", "auto", False),
    "unrolled": ("unrolled", "auto", False),
    "implicit_batched": ("implicit", "batched", False),
    "implicit_petsc": ("implicit", "petsc", False),
    "unrolled_checkpointed": ("unrolled", "auto", True),
}


def solver_options(solver: str, max_it: int, engine: str) -> KSPOptions:
    if solver == "jacobi":
        return KSPOptions(max_it=max_it, engine=engine)
    return KSPOptions.preset(solver, max_it=max_it, engine=engine)


def build_problem(mesh):
    """The benchmark problem on ``fempdl.core.mesh.load("lshape", h=mesh)``, or on a ``.msh`` path."""
    msh = fempdl.core.mesh.load(mesh) if isinstance(mesh, str) else fempdl.core.mesh.load("lshape", h=mesh)
    return msh, fempdl.forms.poisson.problem(msh, controls=("f",))


def make_inputs(seed: int, batch: int, n_control: int, n_out: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Random sources F (leaf, requires grad) and loss weights W; the same in parent and children."""
    rng = np.random.default_rng(seed)
    F = torch.from_numpy(rng.standard_normal((batch, n_control))).requires_grad_()
    W = torch.from_numpy(rng.standard_normal((batch, n_out)))
    return F, W


def stored_bytes(solver: str, K: int, n: int, batch: int) -> int:
    return unrolled.stored_values(UNROLLED_METHOD[solver], K, n, batch) * 8


def checkpoint_limit(solver: str, K: int, n: int, batch: int) -> int:
    """The least max_unrolled_values a checkpointed solve fits in."""
    return unrolled.checkpointed_values(UNROLLED_METHOD[solver], K, n, batch)


def make_layer(prob, solver: str, K: int, variant: str, batch: int) -> SolveLayer:
    diff, engine, checkpointed = VARIANTS[variant]
    limit = checkpoint_limit(solver, K, prob.output_size, batch) if checkpointed else None
    return SolveLayer(prob, solver_options(solver, K, engine), diff=diff, max_unrolled_values=limit)


# ---------------------------------------------------------------- timed work
def layer_call(layer: SolveLayer, F: torch.Tensor, W: torch.Tensor) -> dict:
    """``u = layer(f=F); (u * W).sum().backward()``, timed in its two halves."""
    F.grad = None
    t0 = time.perf_counter()
    u = layer(f=F)
    t1 = time.perf_counter()
    (u * W).sum().backward()
    t2 = time.perf_counter()
    return {"u": u.detach(), "grad": F.grad, "forward": t1 - t0, "backward": t2 - t1, "wall": t2 - t0}


def max_relative_difference(X: torch.Tensor, Y: torch.Tensor) -> float:
    """max over samples of ||x_i - y_i|| / ||y_i||."""
    return float(((X - Y).norm(dim=1) / Y.norm(dim=1)).max())


def round_off_sensitivity(layer: SolveLayer, F: torch.Tensor, u: torch.Tensor) -> float:
    """How much the K-step output moves when F is perturbed at round-off level (relative 1e-15,
    random): the scale below which two implementations of the same iteration cannot agree."""
    generator = torch.Generator().manual_seed(1)
    with torch.no_grad():
        noise = torch.randn(F.shape, generator=generator, dtype=F.dtype)
        u_perturbed = layer(f=F.detach() * (1.0 + ROUND_OFF * noise))
    return max_relative_difference(u_perturbed, u)


def check_outputs(warm: dict, solver: str, sensitivity: float) -> dict:
    """Differences between the variants' outputs and gradients (the warm-up calls)."""
    def diff(a, b, key):
        return max_relative_difference(warm[a][key], warm[b][key])

    check = {
        "u_unrolled_vs_implicit": diff("unrolled", "implicit", "u"),
        "grad_unrolled_vs_implicit": diff("unrolled", "implicit", "grad"),
        "u_unrolled_vs_implicit_petsc": diff("unrolled", "implicit_petsc", "u"),
        "grad_unrolled_vs_implicit_petsc": diff("unrolled", "implicit_petsc", "grad"),
        "u_petsc_vs_batched": diff("implicit_petsc", "implicit_batched", "u"),
        "grad_petsc_vs_batched": diff("implicit_petsc", "implicit_batched", "grad"),
    }
    if "unrolled_checkpointed" in warm:
        check["u_checkpointed_vs_unrolled"] = diff("unrolled_checkpointed", "unrolled", "u")
        check["grad_checkpointed_vs_unrolled"] = diff("unrolled_checkpointed", "unrolled", "grad")
    # Checked: unrolled against the same iteration in the other mode (default engine) and against
    # its checkpointed self; for Jacobi also against PETSc's KSP (round-off stays ~1e-16 there).
    # Recorded only: CG against PETSc's KSPCG (round-off grows with K), CG gradients (implicit is
    # not the VJP of the capped CG map, by design).
    u_keys = ["u_unrolled_vs_implicit"]
    grad_keys = []
    if solver == "jacobi":
        u_keys += ["u_unrolled_vs_implicit_petsc", "u_petsc_vs_batched"]
        grad_keys += ["grad_unrolled_vs_implicit", "grad_unrolled_vs_implicit_petsc", "grad_petsc_vs_batched"]
    if "unrolled_checkpointed" in warm:
        u_keys.append("u_checkpointed_vs_unrolled")
        grad_keys.append("grad_checkpointed_vs_unrolled")
    check["u_change_from_round_off_perturbation"] = sensitivity
    check["tolerance"] = AGREEMENT_TOL
    check["forward_tolerance"] = max(AGREEMENT_TOL, SENSITIVITY_FACTOR * sensitivity)
    check["forward_checked"] = u_keys
    check["forward_agrees"] = all(check[k] <= check["forward_tolerance"] for k in u_keys)
    check["gradients_checked"] = grad_keys
    check["gradients_agree"] = all(check[k] <= AGREEMENT_TOL for k in grad_keys)
    return check
