"""``SolveLayer(diff="unrolled")``: the capped solve re-run in torch, so autograd differentiates the K steps.

The layer's controls become torch operators of the assembled system:

    R = b_base + sum_m C_m m^T   (affine right-hand-side controls, (n, B)),
    A(m) = values0 + J m         (one control the matrix is affine in; entries on A's pattern),

and :func:`fempdl.iterative.unrolled.solve` runs the K iterations on them, so
the gradient is the exact derivative of the capped iterate. Serial only, no
null space, zero Dirichlet values for a matrix control.
"""
from __future__ import annotations

import time

import numpy as np
import scipy.sparse as sp
import torch

from fempdl.core import _dolfinx
from fempdl.iterative import unrolled
from fempdl.iterative.sparse import SparseOperator
from fempdl.solve.assembly import fingerprint, fingerprint_matches
from fempdl.solve.health import CallHealth
from fempdl.solve.linear_system import INITIAL_GUESS, LinearSystem
from fempdl.solve.options import KSPOptions
from fempdl.solve.stats import capped_solve_stats

__all__ = ["UnrolledPath", "unrolled_method", "matrix_jacobian"]

# KSP/PC combinations whose K-step iterate fempdl.iterative.unrolled reproduces.
_METHODS = {("richardson", "jacobi"): "jacobi", ("richardson", "none"): "jacobi",
            ("cg", "jacobi"): "cg", ("cg", "none"): "cg",
            ("gmres", "jacobi"): "gmres", ("gmres", "none"): "gmres"}


def unrolled_method(options: KSPOptions) -> str:
    """The unrolled recurrence ("jacobi", "cg", "gmres") that reproduces ``options``; ValueError if none does."""
    method = _METHODS.get((options.ksp_type, options.pc_type))
    if method is None:
        raise ValueError(f"diff='unrolled' supports {sorted(f'{k}+{p}' for k, p in _METHODS)}, "
                         f"got {options.ksp_type}+{options.pc_type}; use diff='implicit' for it")
    extra = set(options.petsc_options) - {"ksp_richardson_scale"}
    if extra or any(v is not None for v in (options.rtol, options.atol, options.divtol)):
        raise ValueError("diff='unrolled' runs a pure cap: no rtol/atol/divtol and no petsc_options "
                         f"other than ksp_richardson_scale (got {sorted(extra) or 'a tolerance'})")
    return method


class UnrolledPath:
    """The torch operators of one layer's system, cached while the matrix is unchanged, and the unrolled solve.

    ``max_values`` and ``memory_budget`` are the layer's ``max_unrolled_values``
    and ``memory_budget`` (checkpointing and the up-front memory check)."""

    def __init__(self, max_values: int | None, memory_budget: int | None):
        self.max_values, self.memory_budget = max_values, memory_budget
        self._operators = None          # ((names, fingerprint), (A, D^-1, b_base, {name: C_m}))
        self._jacobians: dict = {}      # name -> (fingerprint of a's other inputs, rows, cols, diagonal, v0, J)

    def solve(self, system: LinearSystem, given: dict, batch: int, health: CallHealth | None = None) -> torch.Tensor:
        """u (B, n) = X_K^T for the controls ``given`` (name -> float64 (B, n_m) or (n_m,); the
        key ``initial_guess`` starts the iterations there); the residual ratios measured into ``health``."""
        options, problem = system.options, system.problem
        if not options.capped:
            raise ValueError("diff='unrolled' differentiates a capped iteration: set max_it")
        given = dict(given)
        guess = given.pop(INITIAL_GUESS, None)
        matrix_names = [n for n in given if n in problem.matrix_controls]
        rhs_names = frozenset(given) - set(matrix_names)
        A, P, b_base, mats = self._affine_operators(system, rhs_names)
        if matrix_names:
            A, P = self._matrix(system, matrix_names, given)
        R = b_base.expand(-1, batch)
        for name in sorted(rhs_names):
            R = R + mats[name] @ _columns(given[name])
        t_solve = time.perf_counter()
        X0 = None if guess is None else _columns(guess).expand(-1, batch)
        X = unrolled.solve(unrolled_method(options), A, P if options.pc_type == "jacobi" else None, R,
                           options.max_it, omega=float(options.petsc_options.get("ksp_richardson_scale", 1.0)),
                           restart=options.gmres_restart or 30, max_values=self.max_values, X0=X0,
                           memory_budget=self.memory_budget)
        system.record_batch("forward", options, time.perf_counter() - t_solve,
                            torch.isfinite(X).all(0).numpy(), "unrolled")
        if health is not None:
            _measure_health(health, A, R, X0, X)
        out = X.T
        if out.requires_grad:
            out.register_hook(_count_backward(system, batch))
        return out

    def _affine_operators(self, system: LinearSystem, names: frozenset):
        """Torch A, D^-1 (as PCJACOBI), b_base and C_m, rebuilt when the matrix or the names change."""
        # Keyed by the values of everything else a and L read (a time step, a fixed Function, a control
        # left out of the call), not by the assembled matrix, which only a solve reassembles.
        p = system.problem
        inputs = [obj for obj in (*p.matrix_inputs(), *p.rhs_inputs())
                  if all(obj is not p.control(n) for n in names)]
        if (self._operators is None or self._operators[0][0] != names
                or not fingerprint_matches(self._operators[0][1], inputs, p.V.mesh.comm)):
            try:
                b_base, mats = system.affine_rhs(names)
            except NotImplementedError as err:
                raise NotImplementedError(f"diff='unrolled' is not available here: {err}; use diff='implicit'") \
                    from None
            A = system.constant_matrix()
            d = A.diagonal()
            P = torch.from_numpy(1.0 / np.where(d != 0.0, d, 1.0))[:, None]
            self._operators = ((names, fingerprint(inputs)),
                               (SparseOperator.from_scipy(A), P, torch.from_numpy(b_base)[:, None],
                                {n: SparseOperator.from_scipy(C) for n, C in mats.items()}))
        return self._operators[1]

    def _matrix(self, system: LinearSystem, matrix_names: list, given: dict):
        """A(m) and its inverse diagonal as differentiable functions of the one matrix control."""
        if len(matrix_names) > 1:
            raise NotImplementedError(f"diff='unrolled' takes one matrix control at a time, got {matrix_names}")
        name = matrix_names[0]
        problem = system.problem
        if name in problem.rhs_controls or not problem.homogeneous_bcs():
            raise NotImplementedError(
                f"diff='unrolled' with respect to {name!r} needs zero Dirichlet values and {name!r} absent "
                "from the right-hand side (else b depends on it); use diff='implicit'")
        # A Constant or fixed Function of a(u, v) (a time step) changes v0 and J: rebuild them then.
        fixed = [obj for obj in problem.matrix_inputs() if obj is not problem.control(name)]
        cached = self._jacobians.get(name)
        if cached is None or not fingerprint_matches(cached[0], fixed, problem.V.mesh.comm):
            pattern, v0, J = matrix_jacobian(system, name)
            rows = torch.from_numpy(np.repeat(np.arange(pattern.shape[0]), np.diff(pattern.indptr)))
            cols = torch.from_numpy(pattern.indices.astype(np.int64))
            diagonal = torch.from_numpy(np.flatnonzero(pattern.indices == rows.numpy()))
            self._jacobians[name] = (fingerprint(fixed), rows, cols, diagonal, torch.from_numpy(v0)[:, None],
                                     SparseOperator.from_scipy(J))
        _, rows, cols, diagonal, v0, J = self._jacobians[name]
        values = v0 + J @ _columns(given[name])                               # (nnz, B or 1)
        d = values[diagonal]
        P = 1.0 / torch.where(d == 0, torch.ones_like(d), d)                  # PCJACOBI: zero -> 1
        return _EntryMatrix(rows, cols, values, len(d)), P


def matrix_jacobian(system: LinearSystem, name: str) -> tuple:
    """The matrix as an affine function of control ``name``: entries(m) = v0 + J m.

    Returns (A_pattern, v0, J): A_pattern a scipy CSR matrix whose indptr /
    indices fix the entry order, v0 (nnz,) the entries at m = 0 (Dirichlet
    rows and columns as assembled: identity), J (nnz, n_m) scipy CSR.

    J takes a few assemblies instead of one per DOF of m: the DOFs of m are
    coloured so that no two of one colour share a cell with a common matrix
    entry; assembling with m = the indicator of a colour then yields, for each
    entry, the contribution of the single DOF of that colour touching it.
    Exact for forms affine in m. Serial only.
    """
    p = system.problem
    if name not in p.matrix_controls:
        raise ValueError(f"control {name!r} does not enter the matrix")
    if name not in p.affine_matrix_controls:
        raise NotImplementedError(f"the matrix is not affine in control {name!r}; "
                                  "its unrolled derivative is not available (use diff='implicit')")
    if p.V.mesh.comm.size > 1:
        raise NotImplementedError("the matrix Jacobian is built on one process only")
    m_cells = _dolfinx.cell_dofs(p.control(name).function_space)
    v_cells = _dolfinx.cell_dofs(p.V)
    n_m = p.control_size(name)
    colors = _distance_two_colors(m_cells, v_cells, n_m)
    zero = np.zeros(n_m)
    A0 = system.matrix_with(name, zero).tocsr()
    fixed = system.matrix_with(name, zero, bc_diagonal=0.0).data.copy()   # the part without m, no BC diagonal
    per_color = []
    for color in range(colors.max() + 1):
        Ac = system.matrix_with(name, (colors == color).astype(float), bc_diagonal=0.0)
        if not (np.array_equal(Ac.indptr, A0.indptr) and np.array_equal(Ac.indices, A0.indices)):
            raise RuntimeError("the matrix pattern changed between assemblies")
        per_color.append(Ac.data - fixed)
    # Every (entry, m-DOF) pair that can be nonzero: both entry DOFs and the m-DOF in one cell.
    n = A0.shape[0]
    rows = np.repeat(v_cells, v_cells.shape[1], axis=1)          # (cells, d*d): i
    cols = np.tile(v_cells, (1, v_cells.shape[1]))               # (cells, d*d): j
    keys = (rows.astype(np.int64) * n + cols).ravel()
    csr_keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(A0.indptr)) * n + A0.indices
    entry = np.searchsorted(csr_keys, keys).reshape(rows.shape)  # CSR position of (i, j)
    pairs_e = np.repeat(entry, m_cells.shape[1], axis=1).ravel()
    pairs_k = np.tile(m_cells, (1, entry.shape[1])).ravel()
    pairs = np.unique(np.stack([pairs_e, pairs_k]), axis=1)
    pairs = pairs[:, pairs[1] < n_m]
    values = np.stack(per_color)[colors[pairs[1]], pairs[0]]
    J = sp.csr_matrix((values, (pairs[0], pairs[1])), shape=(A0.nnz, n_m))
    J.eliminate_zeros()
    return A0, A0.data.copy(), J


def _distance_two_colors(m_cells: np.ndarray, v_cells: np.ndarray, n_m: int) -> np.ndarray:
    """Greedy colouring of the DOFs of m: two DOFs get different colours when cells
    containing them share a DOF of the solution space (so they may touch a common
    matrix entry)."""
    n_cells = m_cells.shape[0]
    n_v = int(v_cells.max()) + 1
    cells_of_m = sp.csr_matrix((np.ones(m_cells.size), (m_cells.ravel(), np.repeat(np.arange(n_cells),
                               m_cells.shape[1]))), shape=(int(m_cells.max()) + 1, n_cells))
    v_of_cell = sp.csr_matrix((np.ones(v_cells.size), (np.repeat(np.arange(n_cells), v_cells.shape[1]),
                              v_cells.ravel())), shape=(n_cells, n_v))
    touch = (cells_of_m @ v_of_cell).tocsr()
    graph = (touch @ touch.T).tocsr()
    colors = np.full(graph.shape[0], -1, dtype=np.int64)
    for k in range(graph.shape[0]):
        used = colors[graph.indices[graph.indptr[k]:graph.indptr[k + 1]]]
        free = np.setdiff1d(np.arange(len(used) + 1), used[used >= 0])
        colors[k] = free[0]
    return colors


def _measure_health(health: CallHealth, A, R: torch.Tensor, X0: torch.Tensor | None, X: torch.Tensor) -> None:
    """The call's residual ratios ||r_K|| / ||r_0|| into ``health`` (:mod:`fempdl.solve.health`), columns of
    R and X (n, B)."""
    with torch.no_grad():
        R, X = R.detach(), X.detach()
        starts = R if X0 is None else R - A @ X0.detach()
        health.add_rows(*(M.norm(dim=0).tolist() for M in (R - A @ X, starts, X, R)), lambda: _inf_norm(A))


def _inf_norm(A) -> float:
    """max_i sum_j |A_ij| (over every sample of an :class:`_EntryMatrix`)."""
    if isinstance(A, SparseOperator):
        return float(abs(A.to_scipy()).sum(1).max())
    sums = torch.zeros(A.n, A.values.shape[1], dtype=A.values.dtype).index_add_(0, A.rows, A.values.abs())
    return float(sums.max())


def _columns(m: torch.Tensor) -> torch.Tensor:
    """A control as columns: (B, n) -> (n, B), a shared (n,) -> (n, 1)."""
    return m.unsqueeze(1) if m.dim() == 1 else m.T


def _count_backward(system: LinearSystem, batch: int):
    """A hook that counts the unrolled backward pass as one capped solve per sample."""
    def hook(grad):
        for _ in range(batch):
            system.stats.record("backward", capped_solve_stats(system.options, 0.0, True, "unrolled"))
        return grad
    return hook


class _EntryMatrix:
    """A sparse matrix per column of X, from differentiable entry values (nnz, B)
    on a fixed pattern: (A @ X)[:, b] = A_b X[:, b]."""

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n: int):
        self.rows, self.cols, self.values, self.n = rows, cols, values, n

    @property
    def requires_grad(self) -> bool:
        return self.values.requires_grad

    def __matmul__(self, X: torch.Tensor) -> torch.Tensor:
        return _EntryMatMul.apply(self.values, X, self.rows, self.cols, self.n)


class _EntryMatMul(torch.autograd.Function):
    """(A_b X[:, b])_b from entries (nnz, B or 1); keeps values and X (n, B),
    not the (nnz, B) products autograd would keep through index_add."""

    @staticmethod
    def forward(ctx, values, X, rows, cols, n):
        ctx.save_for_backward(values, X)
        ctx.rows, ctx.cols, ctx.n = rows, cols, n
        return torch.zeros(n, X.shape[1], dtype=X.dtype).index_add_(0, rows, values * X[cols])

    @staticmethod
    def backward(ctx, grad):
        values, X = ctx.saved_tensors
        rows, cols = ctx.rows, ctx.cols
        grad_values = grad_X = None
        if ctx.needs_input_grad[0]:
            grad_values = grad[rows] * X[cols]                              # d(A_b x_b)/d a_ij = x_j
            if values.shape[1] == 1 and grad_values.shape[1] > 1:
                grad_values = grad_values.sum(1, keepdim=True)              # shared matrix
        if ctx.needs_input_grad[1]:
            grad_X = torch.zeros_like(grad).index_add_(0, cols, values * grad[rows])  # A_b^T g_b
            if X.shape[1] == 1 and grad.shape[1] > 1:
                grad_X = grad_X.sum(1, keepdim=True)
        return grad_values, grad_X, None, None, None
