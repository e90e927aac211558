"""Null spaces of discrete operators as arrays of owned DOF values: an orthonormal basis of given
vectors (the exact null space solves project out, or the near null space algebraic multigrid builds
its coarse spaces from), the rigid-body modes of a vector space (elasticity's near null space), and the
constant of each component (what an operator without Dirichlet conditions annihilates)."""
from __future__ import annotations

import numpy as np

from fempdl.core import _dolfinx

__all__ = ["orthonormal", "rigid_body_modes", "constant_modes"]


def orthonormal(vectors, what: str, n: int, comm) -> np.ndarray:
    """Orthonormalise (Gram-Schmidt, global dot products) rows of owned DOF values; ``what`` names
    them in errors (``"nullspace"``)."""
    basis = []
    for i, v in enumerate(vectors):
        v = np.array(v, dtype=np.float64).reshape(-1)
        if v.shape != (n,):
            raise ValueError(f"{what}[{i}] has {v.size} values, expected {n} (owned DOFs of the solution)")
        for w in basis:
            v = v - comm.allreduce(float(w @ v)) * w
        norm = np.sqrt(comm.allreduce(float(v @ v)))
        if not np.isfinite(norm) or norm == 0:
            raise ValueError(f"{what}[{i}] is zero or depends on the vectors before it")
        basis.append(v / norm)
    return np.array(basis).reshape(len(basis), n)


def rigid_body_modes(V) -> np.ndarray:
    """The rigid-body motions of a vector Lagrange space ``V`` (blocked, one component per
    dimension) as owned DOF values: (3, n) in 2D (two translations, one rotation), (6, n) in 3D
    (three translations, three rotations). Linear elasticity's operator annihilates them without
    boundary conditions: its near null space for algebraic multigrid."""
    gdim, bs = V.mesh.geometry.dim, V.dofmap.index_map_bs
    if bs != gdim or gdim not in (2, 3):
        raise ValueError(f"rigid_body_modes needs a vector space with one component per dimension (2 or 3), "
                         f"got {bs} components in {gdim}D")
    nodes = V.tabulate_dof_coordinates()[:V.dofmap.index_map.size_local]
    x, y, z = nodes[:, 0], nodes[:, 1], nodes[:, 2]
    zero, one = np.zeros_like(x), np.ones_like(x)
    if gdim == 2:
        fields = [(one, zero), (zero, one), (-y, x)]
    else:
        fields = [(one, zero, zero), (zero, one, zero), (zero, zero, one),
                  (-y, x, zero), (z, zero, -x), (zero, -z, y)]
    return np.stack([np.stack(f, axis=1).reshape(-1) for f in fields])


def constant_modes(V) -> list[tuple[str, np.ndarray]]:
    """The constant function of each scalar component of ``V`` (each field of a mixed space, each
    component of a vector one) as (label, owned DOF values): 1 on that component's DOFs, 0 elsewhere.
    For Lagrange elements this is the constant 1 (the basis is a partition of unity). An operator
    with no Dirichlet condition on a component, no reaction term and no other boundary term
    annihilates it: a pure-Neumann Laplacian, a pure-traction body's translations, an enclosed
    flow's pressure."""
    n = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
    modes = []
    for label, dofs in _component_dofs(V, "", np.arange(n, dtype=np.int64)):
        mode = np.zeros(n)
        mode[dofs] = 1.0
        modes.append((label, mode))
    return modes


def _component_dofs(V, label: str, dofs: np.ndarray):
    """(label, owned DOF indices in the parent) of every scalar component of ``V``, whose owned DOFs
    sit at ``dofs`` of the parent space."""
    count = V.num_sub_spaces
    if count == 0:
        yield label or "the solution", dofs
        return
    for i in range(count):
        space, local = _dolfinx.collapsed_subspace(V, i)
        yield from _component_dofs(space, f"{label}[{i}]" if label else f"component {i}", dofs[local])
