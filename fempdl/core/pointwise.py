"""Coefficients whose values at the quadrature points are a pointwise map of UFL operands.

A :class:`PointwiseCoefficient` N is a DOLFINx Function on a quadrature space of degree q: one value
(scalar, vector or matrix) per quadrature point of every owned cell, where

    N(x_q) = f(o_1(x_q), ..., o_k(x_q))

for operands o_i (UFL expressions: the unknown, its gradient, x, other coefficients) and a map f that
UFL does not see (a torch network: :class:`fempdl.layer.network.Network` implements
:meth:`PointwiseCoefficient.values_at` and :meth:`PointwiseCoefficient.parameter_vjp`). A form that
holds N is integrated with quadrature degree q
(:func:`fempdl.core.pointwise_forms.with_pointwise_quadrature`), at exactly the
points N holds values at.

Derivatives. UFL sees N as an independent coefficient, so the derivative of a form F in a coefficient c
(the unknown for a Jacobian, a control for a gradient) is completed by the chain rule through the
operands (:func:`fempdl.core.pointwise_forms.total_derivative`):

    dF[c; dc] = dF/dc[dc] + dF/dN[ sum_i N_(i) . do_i/dc[dc] ],

where N_(i) = df/do_i is itself a pointwise coefficient on the same points (:meth:`derivative`; its
derivatives again are N_(i, j), so a second total derivative needs second derivatives of f, and so on).
The Jacobian of a Newton problem with N(u) is thus exact, and keeps Newton's quadratic convergence.

Parameters. f has parameters theta (a network's weights). The gradient of a functional R(N_a, ...) that
holds N and its derivatives N_a is sum_a <dR/dN_a, dN_a/dtheta>: dR/dN_a assembled on N_a's quadrature
space is one cotangent per point (:meth:`cotangent_forms`), and the sum over a is one vector-Jacobian
product through f (:meth:`parameter_vjp`). With R = -F(u, lam) at an adjoint lam, that is dJ/dtheta.

Shapes: operand values are (P, size_i), P the quadrature points of this rank's owned cells, cell by
cell; the values of N_a are (P, prod(shape_a)), shape_a = N's shape + the shapes of the operands in a.

The module knows DOLFINx and UFL but nothing of torch or of solvers.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import ufl

from fempdl.core import _dolfinx

__all__ = ["PointwiseCoefficient", "PointwiseFunction", "view", "operand_functions"]

_MAX_SHAPE_RANK = 2          # a quadrature space of rank > 2 does not compile on DOLFINx 0.5
#: Bytes of recent evaluations (inputs and values) a coefficient keeps, so that a state met again (each
#: sample's solution in its adjoint, after the batch's other solves) is not evaluated again.
RECENT_BYTES = 32 * 2 ** 20


@dataclass
class _Evaluation:
    """One evaluation: the derivative orders, the inputs (operand Functions' and Constants' values, the
    parameters) and the values (alpha -> (P, size_alpha)); whether they were checked (finite, positive)."""

    alphas: tuple
    key: list
    values: dict
    checked: bool

    def matches(self, alphas: tuple, key: list) -> bool:
        return self.alphas == alphas and len(key) == len(self.key) and all(
            a.shape == b.shape and np.array_equal(a, b) for a, b in zip(key, self.key))

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in self.key) + sum(v.nbytes for v in self.values.values())


class PointwiseFunction(dolfinx.fem.Function):
    """A Function holding values of a pointwise coefficient or of one of its derivatives (``alpha``)."""

    root: PointwiseCoefficient
    alpha: tuple

    @property
    def point_size(self) -> int:
        """Values per quadrature point."""
        return math.prod(self.full_shape)


class PointwiseCoefficient(PointwiseFunction):
    """N(x_q) = f(o_1(x_q), ..., o_k(x_q)) at the quadrature points (module docstring).

    Args:
        operands: UFL expressions on one mesh (the unknown, ``grad(u)``, ``SpatialCoordinate``, a coefficient).
        shape: N's value shape: ``()``, ``(m,)`` or ``(a, b)``.
        degree: the quadrature degree of N's points and of every integral N appears in; default twice the
            highest degree among the operands' elements (2 for P1, the degree UFL gives kappa(u) grad u . grad v).
        name: N's name (in forms' printouts, in errors, and the layer's name for its parameters).
        positive: refuse values <= 0 (a conductivity, a viscosity) with a ValueError naming N.

    Subclasses implement :meth:`values_at`, :meth:`parameter_vjp`, :attr:`parameter_count`,
    :meth:`parameter_values` and :meth:`set_parameters`.
    """

    #: What errors call it.
    kind = "pointwise coefficient"

    def __init__(self, operands, *, shape: tuple = (), degree: int | None = None, name: str = "N",
                 positive: bool = False):
        if not isinstance(operands, (tuple, list)) or not operands:
            raise TypeError(f"operands must be a non-empty tuple of UFL expressions (u, grad(u), x, ...), got "
                            f"{type(operands).__name__}")
        ops = []
        for i, op in enumerate(operands):
            try:
                ops.append(ufl.as_ufl(op))
            except Exception:
                raise TypeError(f"operands[{i}] must be a UFL expression (a Function, grad(u), x), got "
                                f"{type(op).__name__}") from None
            if ops[-1].ufl_free_indices:
                raise ValueError(f"operands[{i}] has free indices; give a closed expression (u, grad(u), u * v)")
        msh = _mesh_of(ops)
        shape = tuple(int(s) for s in shape)
        if len(shape) > _MAX_SHAPE_RANK or any(s < 1 for s in shape):
            raise ValueError(f"shape must be (), (m,) or (a, b), got {shape}")
        if degree is None:
            degree = 2 * max((_dolfinx.element_degree(fn.function_space) for fn in operand_functions(ops)), default=1)
        if not isinstance(degree, int) or isinstance(degree, bool) or degree < 1:
            raise ValueError(f"degree must be a positive int (a quadrature degree), got {degree!r}")
        super().__init__(_dolfinx.quadrature_space(msh, degree, shape), name=name)
        self.root, self.alpha, self.full_shape = self, (), shape
        self.operands, self.degree, self.value_shape, self.positive = tuple(ops), degree, shape, bool(positive)
        self.operand_sizes = tuple(math.prod(op.ufl_shape) for op in ops)
        self._mesh = msh
        self._n_cells = msh.topology.index_map(msh.topology.dim).size_local
        self._points = _dolfinx.quadrature_points(msh, degree)
        self._compiled = None                       # the operands' Expression, compiled on first evaluation
        self._functions = {(): self}                # alpha -> Function holding N_alpha
        self._reads = _reads_of(ops)
        self._recent: list[_Evaluation] = []        # recent evaluations, the one the Functions hold first
        #: Seconds spent computing values (operands at the points, the map and its derivatives), and how often.
        self.evaluation_time, self.evaluations = 0.0, 0

    # ------------------------------------------------------------ derivatives
    def derivative(self, alpha: tuple) -> ufl.core.expr.Expr:
        """N_alpha = d^|alpha| f / do_alpha1 ... (``alpha``: operand indices), as a UFL expression of shape
        N's shape + the operands' shapes, held in a quadrature Function made on first use."""
        alpha = tuple(alpha)
        if alpha not in self._functions:
            shape = self.value_shape + sum((self.operands[i].ufl_shape for i in alpha), ())
            size = math.prod(shape)
            fn = PointwiseFunction(_dolfinx.quadrature_space(self._mesh, self.degree, () if size == 1 else (size,)),
                                    name=f"d{len(alpha)}_{self.name}_{'_'.join(map(str, alpha))}")
            fn.root, fn.alpha, fn.full_shape = self, alpha, shape
            self._functions[alpha] = fn
            if self._recent:
                # A form built in the middle of a solve or a backward (a gradient form on first use) is
                # assembled at the state the values were just computed at: evaluate the new derivative there.
                self.refresh()
        return view(self._functions[alpha])

    @property
    def alphas(self) -> tuple:
        """The derivative orders (operand index tuples) whose Functions exist, () first."""
        return tuple(self._functions)

    # ---------------------------------------------------------------- values
    def refresh(self, strict: bool = True) -> None:
        """Evaluate N and every derivative in use at the operands' current values, unless neither they nor
        the parameters changed since the last evaluation, or since one of the recent ones it keeps (on any
        rank: collective). ``strict``: refuse
        non-finite values, or values <= 0 where N is ``positive``, on every rank alike; otherwise (a Newton
        iterate after the first, which may leave the law's domain: an inverted element under log J) write
        them as they are, and the residual shows them as a law undefined there does (Newton's failure, or
        a line search's shorter step)."""
        comm = self._mesh.comm
        alphas = self.alphas
        key = [np.asarray(_value(obj)) for obj in self._reads] + [np.asarray(self.parameter_values())]
        hit = next((i for i, entry in enumerate(self._recent) if entry.matches(alphas, key)), None)
        if comm.size > 1:
            hit = hit if comm.allreduce(hit is not None, op=MPI.LAND) else None
        if hit is None:
            started = time.perf_counter()
            values = self.values_at(self.operand_values(), alphas)
            self.evaluation_time += time.perf_counter() - started
            self.evaluations += 1
            entry = _Evaluation(alphas, [a.copy() for a in key], {}, checked=False)
            for alpha in alphas:
                array = np.asarray(values[alpha], dtype=np.float64)
                expected = (self._n_cells * len(self._points), self._functions[alpha].point_size)
                if array.shape != expected:
                    raise ValueError(f"{self.kind} {self.name!r} gave values of shape {array.shape} for "
                                     f"derivative {alpha}, expected {expected}")
                entry.values[alpha] = array
        else:
            entry = self._recent.pop(hit)
        if strict and not entry.checked:
            for alpha, array in entry.values.items():
                _check_values(self, alpha, array, comm)
            entry.checked = True
        if hit != 0:                      # the first entry's values are those the Functions hold
            for alpha, array in entry.values.items():
                fn = self._functions[alpha]
                fn.x.array.reshape(-1, fn.point_size)[self._cell_dofs(fn)] = array
        self._recent.insert(0, entry)
        while len(self._recent) > 1 and sum(e.nbytes for e in self._recent) > RECENT_BYTES:
            self._recent.pop()

    def operand_values(self) -> list[np.ndarray]:
        """The operands at the quadrature points of this rank's owned cells: one (P, size_i) array each."""
        if self._compiled is None:
            flat = [op[idx] for op in self.operands for idx in np.ndindex(op.ufl_shape)]
            self._compiled = _dolfinx.expression(ufl.as_vector(flat), self._points)
        cells = np.arange(self._n_cells, dtype=np.int32)
        stacked = _dolfinx.evaluate_expression(self._compiled, self._mesh, cells, sum(self.operand_sizes))
        return np.split(stacked, np.cumsum(self.operand_sizes)[:-1], axis=1)

    def cell_average(self) -> dolfinx.fem.Function:
        """N's current values averaged over each cell's points by the quadrature weights (the cell mean on an
        affine mesh), as a DG0 Function named N's name: a field XDMF can store."""
        space = _dolfinx.function_space(self._mesh, "DG", 0, shape=self.value_shape or None)
        weights = _dolfinx.quadrature_weights(self._mesh, self.degree)
        size = math.prod(self.value_shape)
        values = self.x.array.reshape(-1, size)[self._cell_dofs(self)].reshape(self._n_cells, len(weights), size)
        out = dolfinx.fem.Function(space, name=self.name)
        cells = _dolfinx.cell_dofs(space)[:self._n_cells, 0]
        out.x.array.reshape(-1, size)[cells] = np.einsum("q,cqs->cs", weights / weights.sum(), values)
        out.x.scatter_forward()
        return out

    def cotangents(self, vectors: dict) -> dict:
        """Per-point cotangents (P, size_a) from assembled vectors {alpha: owned values on N_alpha's space}."""
        out = {}
        for alpha, vec in vectors.items():
            fn = self._functions[alpha]
            out[alpha] = np.asarray(vec).reshape(-1, fn.point_size)[self._cell_dofs(fn)]
        return out

    def cotangent_forms(self, functional: ufl.Form) -> dict:
        """{alpha: linear form dR/dN_alpha on N_alpha's space} for each N_alpha that the functional R holds."""
        present = set(functional.coefficients())
        return {alpha: ufl.derivative(functional, fn, ufl.TestFunction(fn.function_space))
                for alpha, fn in self._functions.items() if fn in present}

    def _cell_dofs(self, fn) -> np.ndarray:
        return _dolfinx.cell_dofs(fn.function_space)[:self._n_cells].ravel()

    # ------------------------------------------------- the map (subclasses)
    def values_at(self, operands: list[np.ndarray], alphas: tuple) -> dict:
        """{alpha: (P, size_alpha) float64 values of N_alpha} at operand values (P, size_i)."""
        raise NotImplementedError

    def parameter_vjp(self, operands: list[np.ndarray], cotangents: dict) -> np.ndarray:
        """sum_alpha <cotangents[alpha], dN_alpha/dtheta> as a (parameter_count,) float64 array."""
        raise NotImplementedError

    @property
    def parameter_count(self) -> int:
        raise NotImplementedError

    def parameter_values(self) -> np.ndarray:
        """The parameters the values are computed with, (parameter_count,) float64."""
        raise NotImplementedError

    def set_parameters(self, values: np.ndarray) -> None:
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.name!r}, shape={self.value_shape}, degree={self.degree})"


# ------------------------------------------------------------------- forms
def view(fn: PointwiseFunction) -> ufl.core.expr.Expr:
    """``fn`` as a UFL expression of its full shape (a derivative of rank > 2 is stored flat)."""
    if fn.ufl_shape == fn.full_shape:
        return fn
    return _reshaped((lambda k: fn) if fn.point_size == 1 else (lambda k: fn[k]), fn.full_shape)


def _reshaped(component, shape: tuple):
    flat = np.arange(math.prod(shape)).reshape(shape)

    def build(block):
        return [build(b) for b in block] if block.ndim else component(int(block))
    return ufl.as_tensor(build(flat))


# ------------------------------------------------------------------ helpers
def _check_values(coefficient: PointwiseCoefficient, alpha: tuple, array: np.ndarray, comm) -> None:
    bad = int(array.size - np.count_nonzero(np.isfinite(array)))
    low = int(np.count_nonzero(array <= 0)) if coefficient.positive and not alpha and not bad else 0
    if comm.size > 1:
        bad, low = comm.allreduce(bad), comm.allreduce(low)
    what = f"{coefficient.kind} {coefficient.name!r}" + (f" (its derivative {alpha})" if alpha else "")
    if bad:
        raise ValueError(f"{what} gave {bad} NaN/inf value(s) at the quadrature points; check the network (its "
                         "weights, and its inputs: the operands' values, e.g. an iterate of a diverging solve)")
    if low:
        raise ValueError(f"{what} must be > 0 (built with positive=True) but gave {low} value(s) <= 0 at the "
                         "quadrature points; end the network with a positive map (softplus(out) + a floor, exp)")


def _mesh_of(ops: list):
    meshes = {id(fn.function_space.mesh): fn.function_space.mesh for fn in operand_functions(ops)}
    if not meshes:
        domains = {id(d): d for op in ops for d in ufl.domain.extract_domains(op)}
        for domain in domains.values():
            msh = getattr(domain, "ufl_cargo", lambda: None)()
            if msh is not None:
                meshes[id(msh)] = msh
    if len(meshes) != 1:
        raise ValueError("the operands must live on exactly one mesh (hold a Function or the SpatialCoordinate of "
                         f"one mesh), found {len(meshes)}")
    return next(iter(meshes.values()))


def operand_functions(ops) -> list:
    """The DOLFINx Functions the UFL expressions ``ops`` hold."""
    return [c for op in ops for c in ufl.algorithms.extract_coefficients(op) if isinstance(c, dolfinx.fem.Function)]


def _reads_of(ops) -> list:
    found = {}
    for op in ops:
        for obj in (*ufl.algorithms.extract_coefficients(op), *ufl.algorithms.extract_type(op, ufl.Constant)):
            found.setdefault(id(obj), obj)
    return list(found.values())


def _value(obj) -> np.ndarray:
    return obj.x.array if hasattr(obj, "x") else np.asarray(obj.value)
