"""Observation operators on layer tensors: values at points, and mass-matrix inner products and norms.

* :class:`PointObservation`: u -> (u(x_1), ..., u(x_N)) for given points, a sparse (N, n) matrix P
  of basis-function values applied to the owned DOF values (B, n) -> (B, N) (times the block size
  for a vector space: point-major, component-minor). It is linear, so its adjoint is P^T, which
  autograd applies. On a mesh distributed over several ranks each rank holds the columns of its
  owned DOFs and the observations are summed over the ranks: every rank gets all N values.
* :class:`MassInner`: <u, v>_M = u^T M v with the mass matrix (``kind="L2"``:
  M_ij = ∫ phi_i phi_j dx) or the H1 matrix (``kind="H1"``: ∫ phi_i phi_j + ∇phi_i·∇phi_j dx) of a
  space, per sample; :meth:`MassInner.norm` is sqrt(<u, u>_M). Differentiable (M is symmetric:
  d<u, v>/du = M v), and on a distributed mesh collective (PETSc's product fetches the ghost values).

Shapes: u, v (..., n), any leading axes (one sample (n,), a batch (B, n), a rollout's states
(B, T, n)), with n the space's owned DOF values (``problem.output_size`` for the solution,
``problem.control_size(name)`` for a control); results keep the leading axes: (..., N * bs) values,
(...) inner products, u's and v's leading axes broadcast against each other.
Point evaluation supports Lagrange spaces of degree 1 and 2 (scalar or vector) on affine simplex
meshes (straight-sided triangles and tetrahedra), where the pull-back to the reference cell is exact.
"""
from __future__ import annotations

import math

from mpi4py import MPI
import basix
import numpy as np
import scipy.sparse as sp
import torch
import ufl

from fempdl.core import _dolfinx, matrices, parallel
from fempdl.core.problem_base import ProblemBase
from fempdl.iterative.sparse import sparse_to_torch

__all__ = ["PointObservation", "MassInner"]

_REFERENCE_CELLS = {("triangle", 2): basix.CellType.triangle, ("tetrahedron", 3): basix.CellType.tetrahedron}


def _space(problem: ProblemBase, name: str | None):
    # Only the space is read, so a linear and a nonlinear problem serve alike.
    if not isinstance(problem, ProblemBase):
        raise TypeError(f"problem must be a fempdl.Problem or a fempdl.NonlinearProblem (whose space is observed), "
                        f"got {type(problem).__name__}")
    if name is None:
        if problem.fields:
            raise ValueError("the solution of a mixed problem has no single space to observe; observe a field's "
                             "values (problem.split) on problem.field_space(name), or give a control name")
        return problem.V
    return problem.control(name).function_space


class PointObservation(torch.nn.Module):
    """Values of a layer tensor at ``points``: ``obs(u)`` (..., n) -> (..., N * bs), e.g. a rollout's
    states (B, T, n) -> (B, T, N * bs).

    Args:
        problem: the Problem or NonlinearProblem whose solution (``name=None``) or control ``name`` is
            observed.
        points: (N, gdim) or (N, 3) coordinates, the same on every rank. A point outside the mesh is
            an error naming it (a point on a facet is taken in one of its cells).
        name: a control name, or None for the solution.

    Attributes:
        matrix: this rank's (N * bs, n) torch CSR matrix of basis values (float64).
    """

    def __init__(self, problem: ProblemBase, points, *, name: str | None = None):
        super().__init__()
        space = _space(problem, name)
        msh = space.mesh
        self.comm = msh.comm
        self.bs = space.dofmap.index_map_bs
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] not in (msh.geometry.dim, 3) or not np.isfinite(points).all():
            raise ValueError(f"points must be a finite (N, {msh.geometry.dim}) or (N, 3) array, got shape "
                             f"{points.shape}")
        self.points = np.pad(points, ((0, 0), (0, 3 - points.shape[1])))
        rows, columns, weights = self._local_entries(space)
        n_owned = space.dofmap.index_map.size_local
        n_points = len(self.points)
        P = sp.csr_matrix((weights, (rows, columns)), shape=(n_points, n_owned))
        if self.bs > 1:      # component c of point i is row bs i + c, of node j column bs j + c
            P = sp.kron(P, sp.identity(self.bs), format="csr")
        self.matrix = sparse_to_torch(P)

    def _local_entries(self, space):
        """(point, owned node, weight) triplets of this rank's owned nodes."""
        msh = space.mesh
        tdim = msh.topology.dim
        cell_name = _dolfinx.cell_name(msh)
        affine = msh.geometry.dim == tdim and _dolfinx.coordinate_degree(msh) == 1
        if (cell_name, tdim) not in _REFERENCE_CELLS or not affine:
            raise NotImplementedError(f"point observations need an affine simplex mesh (straight triangles or "
                                      f"tetrahedra), got {cell_name} cells in {msh.geometry.dim}D")
        degree = _dolfinx.element_degree(space)
        if _dolfinx.element_family(space) not in ("P", "Q", "Lagrange", "CG") or degree not in (1, 2):
            raise NotImplementedError(f"point observations support Lagrange degree 1 and 2, got "
                                      f"{_dolfinx.element_family(space)} {degree}")
        found, cells = _dolfinx.point_evaluator(msh, self.points)
        # Each point to one rank: the lowest that found it.
        mine = np.zeros(len(self.points), dtype=np.int32)
        mine[found] = 1
        ranks = np.array(self.comm.allgather(mine))
        first = np.where(ranks.any(axis=0), ranks.argmax(axis=0), -1)
        missing = np.flatnonzero(first < 0)
        if len(missing):
            raise ValueError(f"{len(missing)} point(s) lie outside the mesh, e.g. {self.points[missing[0]].tolist()}; "
                             "observe points inside the domain")
        keep = first[found] == self.comm.rank
        found, cells = found[keep], cells[keep]
        x = msh.geometry.x[:, :tdim]
        corners = x[_dolfinx.geometry_dofmap(msh)[cells][:, :tdim + 1]]                 # (k, tdim + 1, tdim)
        jacobians = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))           # columns x_j - x_0
        reference = np.linalg.solve(jacobians, (self.points[found, :tdim] - corners[:, 0])[..., None])[..., 0]
        element = basix.create_element(basix.ElementFamily.P, _REFERENCE_CELLS[cell_name, tdim], degree,
                                       basix.LagrangeVariant.equispaced)
        cell_dofs = _dolfinx.cell_dofs(space)[cells]                                      # (k, dofs per cell)
        values = np.stack([element.tabulate(0, reference[i:i + 1])[0, 0, :, 0] for i in range(len(found))]) \
            if len(found) else np.zeros((0, cell_dofs.shape[1]))
        imap = space.dofmap.index_map
        global_nodes = imap.local_to_global(cell_dofs.reshape(-1).astype(np.int32)).reshape(cell_dofs.shape)
        local = (np.repeat(found, cell_dofs.shape[1]), global_nodes.reshape(-1), values.reshape(-1))
        # A cell's nodes may belong to other ranks: every entry goes to the owner of its node.
        gathered = [np.concatenate(part) for part in zip(*self.comm.allgather(local))]
        start, end = imap.local_range
        own = (gathered[1] >= start) & (gathered[1] < end)
        return gathered[0][own], gathered[1][own] - start, gathered[2][own]

    def forward(self, u: torch.Tensor) -> torch.Tensor:
        """u (..., n) -> (..., N * bs): P applied to every row of the flattened leading axes."""
        n_obs, n = self.matrix.shape
        _check_floating("u", u)
        if u.dim() == 0 or u.shape[-1] != n:
            raise ValueError(f"u must have shape (..., {n}): {n} owned DOF values last, e.g. (B, {n}) or a "
                             f"rollout's (B, T, {n}); got {tuple(u.shape)}")
        rows = _rows(u, n)
        local = (self.matrix @ rows.T).T
        out = parallel.allreduce_sum(local, self.comm)
        return out.reshape(*u.shape[:-1], n_obs).to(u.dtype)


class MassInner(torch.nn.Module):
    """<u, v>_M per sample, with M the L2 (mass) or H1 matrix of a space; ``inner(u, v)`` (..., n) -> (...),
    ``inner.norm(u)`` its square root.

    Args:
        problem, name: the space, as for :class:`PointObservation`.
        kind: ``"L2"`` (∫ u v dx) or ``"H1"`` (∫ u v + ∇u·∇v dx).
    """

    def __init__(self, problem: ProblemBase, *, name: str | None = None, kind: str = "L2"):
        super().__init__()
        if kind not in ("L2", "H1"):
            raise ValueError(f"kind must be 'L2' or 'H1', got {kind!r}")
        space = _space(problem, name)
        trial, test = ufl.TrialFunction(space), ufl.TestFunction(space)
        form = ufl.inner(trial, test) * ufl.dx
        if kind == "H1":
            form = form + ufl.inner(ufl.grad(trial), ufl.grad(test)) * ufl.dx
        self.kind = kind
        self.size = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
        self._M = matrices.create_matrix(_dolfinx.compile_form(form))
        matrices.assemble_matrix_into(self._M, _dolfinx.compile_form(form))
        self._x, self._y = self._M.createVecs()
        self.comm = space.mesh.comm

    def apply(self, u: np.ndarray) -> np.ndarray:
        """M u for the rows of u (B, n): this rank's owned rows (collective)."""
        out = np.empty_like(u)
        for i, row in enumerate(u):
            self._x.setArray(row)
            self._M.mult(self._x, self._y)
            out[i] = self._y.getArray(readonly=True)
        return out

    def forward(self, u: torch.Tensor, v: torch.Tensor | None = None) -> torch.Tensor:
        """<u, v>_M over the last axis: u, v (..., n) -> (...), leading axes broadcast; ``v=None``: <u, u>_M."""
        for label, t in (("u", u), ("v", u if v is None else v)):
            _check_floating(label, t)
            if t.dim() == 0 or t.shape[-1] != self.size:
                raise ValueError(f"{label} must have shape (..., {self.size}): {self.size} owned DOF values "
                                 f"last, e.g. (B, {self.size}); got {tuple(t.shape)}")
        if v is None:             # one operand: M u is computed once
            rows = _rows(u, self.size)
            return _MassInnerFunction.apply(rows, rows, self).reshape(u.shape[:-1])
        try:
            lead = torch.broadcast_shapes(u.shape[:-1], v.shape[:-1])
        except RuntimeError:
            raise ValueError(f"u {tuple(u.shape)} and v {tuple(v.shape)} have leading axes that do not broadcast; "
                             "give equal leading axes, or 1 where one is shared") from None
        u2, v2 = (_rows(t.expand(*lead, self.size), self.size) for t in (u, v))
        return _MassInnerFunction.apply(u2, v2, self).reshape(lead)

    def norm(self, u: torch.Tensor) -> torch.Tensor:
        return self(u).clamp_min(0.0).sqrt()

    def close(self) -> None:
        for obj in (self._M, self._x, self._y):
            obj.destroy()


class _MassInnerFunction(torch.autograd.Function):
    @staticmethod
    def forward(ctx, u, v, inner: MassInner):
        Mv = torch.from_numpy(inner.apply(v.detach().numpy()))
        Mu = Mv if u is v else torch.from_numpy(inner.apply(u.detach().numpy()))
        ctx.save_for_backward(Mu, Mv)
        local = (u.detach() * Mv).sum(1)
        total = local.numpy().copy()
        inner.comm.Allreduce(MPI.IN_PLACE, total, op=MPI.SUM)
        return torch.from_numpy(total)

    @staticmethod
    def backward(ctx, grad):
        Mu, Mv = ctx.saved_tensors
        return grad[:, None] * Mv, grad[:, None] * Mu, None


def _rows(u: torch.Tensor, n: int) -> torch.Tensor:
    """u (..., n) as float64 rows (prod(...), n); explicit, since reshape(-1, 0) is ambiguous on a rank of a
    distributed mesh that owns no DOFs (n = 0)."""
    return u.reshape(math.prod(u.shape[:-1]), n).to(torch.float64)


def _check_floating(label: str, t: torch.Tensor) -> None:
    """Refuse an integer (or complex, bool) tensor, as the layers do: its values would be truncated."""
    if t.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"{label} has dtype {t.dtype}; use float32 or float64 (e.g. {label}.double())")
