"""What the assembled system of a Problem keeps between calls, and the conversions it needs.

* :class:`ControlValues` sets the control Functions sample by sample and restores them afterwards;
* :func:`fingerprint` / :func:`fingerprint_matches` tell whether the coefficients and constants an
  assembled object was built from still have their values (on every rank);
* :class:`KeptMatrices` keeps copies of per-sample matrices of recent forward calls for their adjoints;
* :class:`Timer` adds the seconds of a block to a stats counter;
* :func:`check_operator` refuses an assembled matrix with an empty row (singular) or a non-finite entry;
* :func:`assemble_scipy` gives an assembled form as a scipy CSR matrix.
"""
from __future__ import annotations

import time
from collections.abc import Mapping

from mpi4py import MPI
import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from fempdl.core import matrices
from fempdl.core.problem import Problem
from fempdl.solve.petsc import petsc_to_scipy

__all__ = ["check_operator", "operator_defect", "check_symmetric_factor", "check_symmetric", "SYMMETRIC_PC_TYPES",
           "ControlValues", "KeptMatrices", "Timer", "attach_nullspace", "set_owned", "fingerprint",
           "fingerprint_matches", "assemble_scipy"]


class KeptMatrices:
    """Copies of the per-sample matrices of recent forward calls, for their adjoints.

    An adjoint finds its call's matrices by the call's serial number
    (:meth:`~fempdl.solve.call_state.CallState.new_call`), never by the
    controls' values: two calls with the same matrix controls may differ in
    what else the matrix reads (a dt set between them). The oldest call is
    dropped beyond ``calls`` calls or ``max_bytes`` of matrix values (unrolled
    multi-step chains run several forward calls before their adjoints); an
    adjoint whose call was dropped assembles again, with the call's state put
    back."""

    def __init__(self, calls: int = 4, max_bytes: int = 256 * 2 ** 20):
        self._calls, self._max_bytes = calls, max_bytes
        self._entries: list[KeptCall] = []

    def start(self, call: int, batch: int) -> KeptCall | None:
        if self._calls == 0:
            return None
        spare = self._entries.pop(0).mats if len(self._entries) >= self._calls else []
        entry = KeptCall(call, batch, spare, self._max_bytes)
        self._entries.append(entry)
        return entry

    def find(self, call: int | None, batch: int) -> KeptCall | None:
        for entry in reversed(self._entries):         # the newest: a call solved again keeps its matrices anew
            if call is not None and entry.matches(call, batch):
                return entry
        return None

    def clear(self) -> None:
        for entry in self._entries:
            entry.destroy()
        self._entries.clear()


class KeptCall:
    def __init__(self, call: int, batch: int, spare: list, max_bytes: int):
        self.call, self.batch, self.mats, self._spare, self._max_bytes = call, batch, [], spare, max_bytes
        self.complete = True

    def append(self, A: PETSc.Mat) -> None:
        if not self.complete:
            return
        if (len(self.mats) + 1) * A.getInfo()["nz_used"] * 8 > self._max_bytes:
            self.complete = False          # too big to keep: the adjoint assembles again
            self.destroy()
            return
        if self._spare:
            target = self._spare.pop()
            A.copy(target, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)
        else:
            target = A.duplicate(copy=True)
        self.mats.append(target)

    def matches(self, call: int, batch: int) -> bool:
        return self.complete and call == self.call and batch == self.batch == len(self.mats)

    def restore(self, i: int, A: PETSc.Mat) -> None:
        """Copy sample ``i``'s matrix into ``A`` (same pattern)."""
        self.mats[i].copy(A, structure=PETSc.Mat.Structure.SAME_NONZERO_PATTERN)

    def destroy(self) -> None:
        for mat in self.mats + self._spare:
            mat.destroy()
        self.mats, self._spare = [], []


class Timer:
    """Adds the seconds spent inside a ``with`` block to a counter of ``stats``."""

    def __init__(self, stats, field: str):
        self._stats, self._field = stats, field

    def __enter__(self):
        self._t0 = time.perf_counter()

    def __exit__(self, *exc):
        setattr(self._stats, self._field, getattr(self._stats, self._field) + time.perf_counter() - self._t0)


class ControlValues:
    """Sets control Functions (and networks' parameters) per sample and restores their values on exit
    (saved at the first :meth:`set_sample`: a call that never sets them, a batched affine solve, copies
    nothing). With ``refresh`` each sample's networks are evaluated at the values set (a linear problem's
    operands are its coefficients; a Newton system evaluates them at each iterate instead)."""

    def __init__(self, problem: Problem, controls: Mapping[str, np.ndarray], refresh: bool = True):
        self._problem = problem
        self._values = controls
        self._refresh = refresh and bool(problem.networks)
        self._fns = self._saved = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self._saved is not None:
            for n, fn in self._fns.items():
                fn.x.array[:] = self._saved[n]
            for n, values in self._saved_parameters.items():
                self._problem.networks[n].set_parameters(values)

    def set_sample(self, i: int) -> None:
        networks = self._problem.networks
        if self._saved is None:
            self._fns = {n: self._problem.control(n) for n in self._values if n not in networks}
            self._sizes = {n: self._problem.control_size(n) for n in self._fns}
            self._saved = {n: fn.x.array.copy() for n, fn in self._fns.items()}
            self._saved_parameters = {n: networks[n].parameter_values().copy() for n in self._values if n in networks}
        for n, fn in self._fns.items():
            set_owned(fn, self._values[n][i], self._sizes[n])
        for n in self._saved_parameters:
            networks[n].set_parameters(self._values[n][i])
        if self._refresh:
            self._problem.refresh_networks()

    def zeroed(self, names):
        return Zeroed([self._problem.control(n) for n in names])


class Zeroed:
    def __init__(self, fns):
        self._fns = fns

    def __enter__(self):
        self._saved = [fn.x.array.copy() for fn in self._fns]
        for fn in self._fns:
            fn.x.array[:] = 0.0

    def __exit__(self, *exc):
        for fn, saved in zip(self._fns, self._saved):
            fn.x.array[:] = saved


def attach_nullspace(A: PETSc.Mat, basis: np.ndarray, *, near: bool = False):
    """Attach the (orthonormal, owned values) null space of A and A^T to A, or with ``near`` its near
    null space (for algebraic multigrid: it changes no solution). Returns the NullSpace (or None)."""
    if not len(basis):
        return None
    vectors = []
    for values in basis:
        vec = A.createVecRight()
        vec.setArray(values)
        vectors.append(vec)
    nsp = PETSc.NullSpace().create(vectors=vectors, comm=A.getComm())
    if near:
        A.setNearNullSpace(nsp)
    else:
        A.setNullSpace(nsp)
        A.setTransposeNullSpace(nsp)
    for vec in vectors:
        vec.destroy()
    return nsp


def set_owned(fn, values: np.ndarray, n_owned: int) -> None:
    """Write owned DOF values into a Function and update its ghosts."""
    fn.x.array[:n_owned] = values
    fn.x.scatter_forward()


def fingerprint(inputs) -> tuple:
    return tuple(value_of(obj).copy() for obj in inputs)


def fingerprint_matches(fp: tuple, inputs, comm) -> bool:
    """Whether every input still has its fingerprinted value, on every rank (the
    answer decides on collective reassembly, so all ranks must agree)."""
    local = len(fp) == len(inputs) and all(np.array_equal(old, value_of(obj)) for old, obj in zip(fp, inputs))
    return comm.allreduce(local, op=MPI.LAND) if comm.size > 1 else local


def value_of(obj) -> np.ndarray:
    """The values an assembled form depends on: a Function's array or a Constant's value."""
    if hasattr(obj, "x"):
        return obj.x.array
    return np.asarray(obj.value)


def assemble_scipy(form) -> sp.csr_matrix:
    """A compiled bilinear form assembled without boundary conditions, as scipy CSR (local rows)."""
    A = matrices.create_matrix(form)
    try:
        matrices.assemble_matrix_into(A, form)
        return petsc_to_scipy(A)
    finally:
        A.destroy()


def without_bc_entries(G: np.ndarray, problem) -> np.ndarray:
    """A float64 copy of G (B, n) with the Dirichlet DOFs' entries zeroed: u = g on the boundary does not
    depend on the controls, so no gradient comes back through those entries."""
    G = np.array(G, dtype=np.float64)
    if len(problem.bc_dofs):
        G[:, problem.bc_dofs] = 0.0
    return G


def check_operator(A: PETSc.Mat, controls: list[str], also: str = "") -> None:
    """Raise ValueError on every rank when the assembled ``A`` has a NaN/inf entry or an empty row
    (:func:`operator_defect`). The message names ``controls``, the matrix controls set for this assembly,
    and ``also``, another cause to check."""
    what = operator_defect(A)
    if what is None:
        return
    source = (f"control(s) {controls}" if controls else
              "the problem's coefficients (no matrix control was passed: check its fixed Functions and Constants)")
    raise ValueError(f"the assembled matrix has {what} with {source}; check for a zero or non-finite "
                     f"coefficient (e.g. kappa = 0 somewhere){also} or a missing Dirichlet condition")


#: A row whose product with a component's constant is below this fraction of the row's absolute sum is
#: zero to round-off (measured: 1e-16 to 6e-16 on P1/P2 in 2D/3D); a ratio r means a condition number of at
#: least about 1/r, so below this a solve keeps at most three digits.
SINGULAR_ROW_RATIO = 1e-13


def constant_mode_ratio(A: PETSc.Mat, mode: np.ndarray) -> float:
    """max_i |(A m)_i| / sum_j |a_ij| over A's rows: about 1e-16 when the constant ``mode`` (owned DOF
    values) is in A's null space, O(1) on a Dirichlet row or a row with a reaction or boundary term.
    Row by row, so neither a coefficient's scale nor the 1 of a Dirichlet row sets the threshold."""
    indptr, _, data = A.getValuesCSR()
    abs_sums = np.add.reduceat(np.abs(data), indptr[:-1]) if len(data) else np.zeros(len(indptr) - 1)
    v = A.createVecRight()
    w = A.createVecLeft()
    v.setArray(mode)
    A.mult(v, w)
    ratio = np.abs(w.getArray(readonly=True)) / np.where(abs_sums > 0, abs_sums, 1.0)
    v.destroy()
    w.destroy()
    local = float(ratio.max()) if len(ratio) else 0.0
    comm = A.getComm()
    return comm.tompi4py().allreduce(local, op=MPI.MAX) if comm.getSize() > 1 else local


def check_not_singular(A: PETSc.Mat, modes) -> None:
    """Refuse, on every rank, an ``A`` that annihilates one of the constant ``modes``
    (:func:`fempdl.core.nullspaces.constant_modes`): a problem with no Dirichlet condition on that
    component and no declared null space, whose solution (a factorisation returns one of many) and
    gradients are not unique."""
    for label, mode in modes:
        if constant_mode_ratio(A, mode) <= SINGULAR_ROW_RATIO:
            raise ValueError(
                f"the system is singular: the operator maps the constant {label} to zero (no Dirichlet "
                "condition on it, no reaction or boundary term), so its solution is defined up to that "
                "constant and gradients through it are not; add a Dirichlet condition, or declare the null "
                "space (Problem(..., nullspace=[ones on that component]): solves then return the solution "
                "orthogonal to it, with a load that has no part along it)")


def operator_defect(A: PETSc.Mat) -> str | None:
    """What makes the assembled ``A`` unusable, the same answer on every rank: ``"NaN or inf entries"``,
    ``"N empty rows (it is singular)"``, or ``None``.

    An empty row is a singular matrix, and neither a factorisation nor Jacobi says so: MUMPS returns
    a tiny or huge finite vector, PCJACOBI takes 1 for the zero diagonal and iterates on. It is what
    a zero coefficient gives (kappa = 0 on a node's support); Dirichlet rows hold 1. Costs a pass
    over the entries."""
    # The Frobenius norm, a sum over every entry, carries a NaN through (the largest row sum of the
    # infinity norm drops a NaN row: NaN > max is false). Past 1e154 it overflows: look at the entries then.
    finite = np.isfinite(A.norm(PETSc.NormType.FROBENIUS))
    if not finite:
        finite = bool(np.isfinite(A.getValuesCSR()[2]).all())
        comm = A.getComm()
        if comm.getSize() > 1:
            finite = comm.tompi4py().allreduce(finite, op=MPI.LAND)
    diagonal = A.getDiagonal()
    suspects = np.flatnonzero(diagonal.getArray(readonly=True) == 0.0)
    diagonal.destroy()
    empty = 0
    if len(suspects):                   # rare: a zero diagonal entry; is its whole row zero?
        indptr, _, data = A.getValuesCSR()
        nonzero = np.concatenate([[0], np.cumsum(data != 0.0)])
        empty = int(np.count_nonzero(nonzero[indptr[suspects + 1]] == nonzero[indptr[suspects]]))
    comm = A.getComm()
    if comm.getSize() > 1:
        empty = comm.tompi4py().allreduce(empty)
    if finite and not empty:
        return None
    return "NaN or inf entries" if not finite else f"{empty} empty row{'s' if empty > 1 else ''} (it is singular)"


#: Preconditioners that read only one triangle of A: right only for a symmetric A.
SYMMETRIC_PC_TYPES = frozenset({"cholesky", "icc"})


def check_symmetric_factor(options, problem) -> None:
    """Refuse a Cholesky (or ICC) solve, forward or adjoint, of a problem not declared symmetric: it reads
    one triangle of A and would silently solve another system."""
    used = {o.pc_type for o in (options, options.adjoint_options)} & SYMMETRIC_PC_TYPES
    if used and not hasattr(problem, "symmetric"):        # a NonlinearProblem: J(u) of a residual
        raise ValueError(f"pc_type={sorted(used)[0]!r} factorises A as symmetric, and a NonlinearProblem's "
                         "Jacobian is solved as a general matrix; use the 'lu' preset")
    if used and not problem.symmetric:
        raise ValueError(f"pc_type={sorted(used)[0]!r} factorises A as symmetric, but this problem is not declared "
                         "symmetric; use the 'lu' preset, or build the Problem with symmetric=True if a(u, v) = "
                         "a(v, u) for every control value")


def check_symmetric(A: PETSc.Mat) -> None:
    """Raise ValueError on every rank unless the assembled ``A`` is symmetric to round-off (one pass over A)."""
    scale = A.norm(PETSc.NormType.INFINITY)
    if not A.isSymmetric(tol=1e-12 * scale):
        raise ValueError("the problem is declared symmetric (Problem(..., symmetric=True)) but its assembled matrix "
                         "is not: a Cholesky factorisation would solve another system; use the 'lu' preset or drop "
                         "symmetric=True")
