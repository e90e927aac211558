"""A linear variational problem with named controls, and what depends on what.

``Problem(a, L, bcs, controls={name: Function})`` describes: find u in V with
u = g on the Dirichlet boundary and

    a(u, v; m) = L(v; m)   for all v in V0,

where the controls m are DOLFINx Functions that appear as coefficients in ``a``
and/or ``L``. A Problem compiles ``a`` and ``L`` once and answers the questions
that decide how much work a solve needs ("model only what a scene requires"):

* which controls enter the matrix (``matrix_controls``): if none of those is
  passed, the matrix is assembled once and reused for every sample and call;
* which controls enter the right-hand side affinely with a constant
  coefficient (``affine_rhs_controls``, e.g. a source f or an initial state u0):
  their contribution is one sparse product with an assembled matrix
  C_m = dL/dm, and so is their gradient (C_m^T lam);
* the derivative forms of every other control, built and compiled only when a
  gradient with respect to it is first requested.

Control gradients follow from the residual F(u; v) = a(u, v) - L(v) and the
adjoint solution lam of A^T lam = dJ/du (BC entries of dJ/du zeroed):

    dJ/dm = -action(adjoint(derivative(F, m, TrialFunction(M))), lam).

The module knows DOLFINx and UFL but nothing of torch or of solvers.
"""
from __future__ import annotations

import keyword
from types import MappingProxyType
from typing import Callable, Mapping

import dolfinx.fem
import numpy as np
import ufl
from ufl.algorithms import expand_derivatives

from mpi4py import MPI

from fempdl.core import _dolfinx
from fempdl.core.nullspaces import orthonormal

_LAND = MPI.LAND

__all__ = ["Problem"]


class Problem:
    """A linear variational problem a(u, v) = L(v) with named controls.

    Args:
        a: bilinear UFL form (test function number 0, trial function number 1).
        L: linear UFL form on the same test space.
        bcs: Dirichlet conditions on the trial space (``dolfinx.fem.dirichletbc``).
        controls: ``{name: dolfinx.fem.Function}``; each Function must appear as a
            coefficient of ``a`` or ``L`` and live on the same mesh.

    Attributes:
        V: the solution space; ``u`` and ``lam`` are work Functions on it.
        control_names: the control names in the order given.
        matrix_controls: names of controls that ``a`` depends on.
        rhs_controls: names of controls that ``L`` depends on.
        affine_rhs_controls: controls that enter only ``L``, linearly, with a
            coefficient that depends on no control (C_m = dL/dm is constant).
        affine_matrix_controls: matrix controls the matrix is affine in.
        fields: ``{name: owned DOF indices}`` of the subspaces of a mixed
            solution space (e.g. ``"u"`` and ``"p"``), in each collapsed
            subspace's DOF order; empty for a single space. Fieldsplit
            preconditioners and :meth:`split` use them.
        nullspace: orthonormal (k, n) array spanning the null space of A and of
            A^T (owned DOF values), e.g. the pressure constant of an enclosed
            flow; (0, n) when A is regular. Solves return the solution
            orthogonal to it (see :class:`fempdl.ksp_adjoint.CappedSolver`).
        near_nullspace: orthonormal (k, n) array of the near null space handed
            to algebraic multigrid; (0, n) when none was given.

    Keyword Args:
        fields: ``{name: subspace index}`` of a mixed solution space.
        nullspace: vectors (owned DOF values, any basis) spanning the common
            null space of A and A^T.
        constants: ``{name: dolfinx.fem.Constant}`` of the forms (a time step,
            a viscosity) that the user may change between solves through
            ``problem.constants[name].value``; a change is seen at the next solve.
        near_nullspace: vectors (owned DOF values, any basis) that A nearly
            annihilates away from the boundary, e.g. the rigid-body modes of
            elasticity (:func:`fempdl.core.nullspaces.rigid_body_modes`); handed to PETSc as the
            operator's near null space, which algebraic multigrid (GAMG) uses to
            build its coarse spaces. It changes no solution, only how fast AMG
            converges.
    """

    def __init__(self, a: ufl.Form, L: ufl.Form, bcs=(), controls: Mapping | None = None, *,
                 fields: Mapping[str, int] | None = None, nullspace=(), constants: Mapping | None = None,
                 near_nullspace=()):
        if not isinstance(a, ufl.Form) or len(a.arguments()) != 2:
            raise TypeError(f"a must be a bilinear UFL form (two arguments), got {_describe_form(a)}")
        if not isinstance(L, ufl.Form) or len(L.arguments()) != 1:
            raise TypeError(f"L must be a linear UFL form (one argument), got {_describe_form(L)}")
        test, trial = sorted(a.arguments(), key=lambda arg: arg.number())
        if L.arguments()[0].ufl_function_space() != test.ufl_function_space():
            raise ValueError("L's test space differs from a's test space; build both with the same TestFunction")
        self.V = trial.ufl_function_space()
        self.a = a
        self.L = L
        self.bcs = tuple(bcs)
        for i, bc in enumerate(self.bcs):
            if not _dolfinx.is_dirichlet_bc(bc):
                raise TypeError(f"bcs[{i}] must be a dolfinx.fem.dirichletbc, got {type(bc).__name__}")
            if not _dolfinx.bc_on_space(bc, self.V):
                raise ValueError(f"bcs[{i}] is not defined on the trial space of a (or a subspace of it); "
                                 "create it with the same FunctionSpace")
        self._controls = _validated_controls(controls or {}, a, L, self.V.mesh)
        self.control_names = tuple(self._controls)

        self.u = dolfinx.fem.Function(self.V, name="u")
        self.lam = dolfinx.fem.Function(self.V, name="adjoint")
        self.a_form = _dolfinx.compile_form(a)
        self.L_form = _dolfinx.compile_form(L)

        a_coeffs, L_coeffs = set(a.coefficients()), set(L.coefficients())
        self.matrix_controls = frozenset(n for n, fn in self._controls.items() if fn in a_coeffs)
        self.rhs_controls = frozenset(n for n, fn in self._controls.items() if fn in L_coeffs)
        self._rhs_derivatives = {n: self._rhs_derivative(n) for n in self.rhs_controls}
        self.affine_rhs_controls = frozenset(
            n for n, dL in self._rhs_derivatives.items()
            if n not in self.matrix_controls and not self._depends_on_controls(dL))
        # Matrix controls the matrix is affine in (A(m) = A0 + sum_k m_k A_k).
        # (The direction is a third argument: a already has a test and a trial function.)
        self.affine_matrix_controls = frozenset(
            n for n in self.matrix_controls
            if self._controls[n] not in set(expand_derivatives(ufl.derivative(
                a, self._controls[n], ufl.Argument(self._controls[n].function_space, 2))).coefficients()))
        self._gradient_forms: dict = {}
        self._rhs_matrix_forms: dict = {}

        imap = self.V.dofmap.index_map
        self._n_owned = imap.size_local * self.V.dofmap.index_map_bs
        self.bc_dofs = _dolfinx.bc_dofs_owned(self.bcs, self._n_owned)
        self._field_spaces = {}
        self.fields = {}
        for name, index in (fields or {}).items():
            space, dofs = _dolfinx.collapsed_subspace(self.V, index)
            self._field_spaces[name] = space
            self.fields[name] = dofs
        self.nullspace = orthonormal(nullspace, "nullspace", self._n_owned, self.V.mesh.comm)
        self.near_nullspace = orthonormal(near_nullspace, "near_nullspace", self._n_owned, self.V.mesh.comm)
        self.constants = MappingProxyType(_validated_constants(constants or {}))

    @property
    def enclosed(self) -> bool:
        """Whether A has a null space (an enclosed flow's pressure constant) that solves project out."""
        return len(self.nullspace) > 0

    # ------------------------------------------------------------------ sizes
    @property
    def output_size(self) -> int:
        """Number of owned DOF values of the solution on this rank."""
        return self._n_owned

    def control(self, name: str) -> dolfinx.fem.Function:
        """The Function that holds control ``name``."""
        self._check_name(name)
        return self._controls[name]

    def control_size(self, name: str) -> int:
        """Number of owned DOF values a tensor for control ``name`` must have."""
        space = self.control(name).function_space
        return space.dofmap.index_map.size_local * space.dofmap.index_map_bs

    def dof_coordinates(self, name: str | None = None) -> np.ndarray:
        """Coordinates (n_owned, 3) of the owned DOFs of the solution (``name=None``)
        or of control ``name``, in the order tensors use. For a vector (blocked)
        space they are the nodes' coordinates, (n_owned / gdim, 3): tensor entry
        gdim * i + c is component c at node i."""
        space = self.V if name is None else self.control(name).function_space
        n = space.dofmap.index_map.size_local
        return space.tabulate_dof_coordinates()[:n]

    def interpolate(self, expression: Callable[[np.ndarray], np.ndarray], name: str | None = None) -> np.ndarray:
        """Owned DOF values of ``expression`` (x of shape (3, N) -> values (N,))
        interpolated into the solution space or the space of control ``name``."""
        space = self.V if name is None else self.control(name).function_space
        fn = dolfinx.fem.Function(space)
        fn.interpolate(expression)
        n = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
        return fn.x.array[:n].copy()

    def split(self, values) -> dict:
        """The field parts of solution values (..., n) (a tensor or an array):
        ``{name: values[..., fields[name]]}``, each in its collapsed subspace's
        DOF order (so a velocity can be fed back as a control on that space)."""
        if not self.fields:
            raise ValueError("this problem has a single solution space; there is nothing to split")
        if values.shape[-1] != self._n_owned:
            raise ValueError(f"values have {values.shape[-1]} entries in the last dimension, expected "
                             f"{self._n_owned} (problem.output_size)")
        return {name: values[..., dofs] for name, dofs in self.fields.items()}

    def to_function(self, values, name: str | None = None) -> dolfinx.fem.Function:
        """A new Function holding ``values`` (owned DOF values, shape (n,); a
        tensor or an array), ghosts updated, named ``name`` (``"u"`` for the output).

        ``name`` picks the space: a control name (its space; ``control_size``
        values), a field of a mixed solution such as ``"u"`` or ``"p"`` (the
        collapsed subspace; either that field's values, as :meth:`split` gives
        them, or the whole solution), or ``None``/``"u"`` for the solution space
        (``output_size`` values; the whole mixed space for a flow problem).
        Use it to post-process or write a layer's output (:mod:`fempdl.core.io`).
        """
        space, kind = self._space_of(name)
        array = _as_array(values, "values")
        n = _owned_size(space)
        if kind == "field" and array.shape == (self._n_owned,):
            array = array[self.fields[name]]
        if array.shape != (n,):
            expected = f"({n},)" + (f" or ({self._n_owned},) (the whole solution)" if kind == "field" else "")
            raise ValueError(f"values for {name!r} must have shape {expected} (owned DOFs of its space), got "
                             f"{tuple(array.shape)}; pass one sample (values[i]) of a batch")
        fn = dolfinx.fem.Function(space, name="u" if name is None else name)
        fn.x.array[:n] = array
        fn.x.scatter_forward()
        return fn

    def from_function(self, fn: dolfinx.fem.Function, name: str | None = None) -> np.ndarray:
        """The owned DOF values (n,) (float64) of Function ``fn`` in the space that
        ``name`` picks (as in :meth:`to_function`), the order a layer's tensors use
        (``torch.from_numpy`` makes it a tensor). A Function on another space of
        the same mesh is interpolated into that space first; on the same space
        the values are copied exactly, so ``from_function(to_function(x))`` is x."""
        if not isinstance(fn, dolfinx.fem.Function):
            raise TypeError(f"fn must be a dolfinx.fem.Function, got {type(fn).__name__}")
        space, _ = self._space_of(name)
        if fn.function_space != space:
            if fn.function_space.mesh is not space.mesh:
                raise ValueError(f"fn lives on a different mesh than the space of {name!r}; "
                                 "interpolate it onto this problem's mesh first")
            target = dolfinx.fem.Function(space)
            target.interpolate(fn)
            fn = target
        return np.array(fn.x.array[:_owned_size(space)], dtype=np.float64)

    def function_space(self, name: str | None = None):
        """The DOLFINx space a tensor for ``name`` lives in: a control's space, a
        field's collapsed subspace, or (``None``/``"u"``) the solution space."""
        return self._space_of(name)[0]

    def _space_of(self, name: str | None):
        """(space, kind) of ``name``: a control, a field of a mixed solution, or the output."""
        if name is not None and name in self._controls:
            return self._controls[name].function_space, "control"
        if name is not None and name in self._field_spaces:
            return self._field_spaces[name], "field"
        if name is None or name == "u":
            return self.V, "output"
        raise ValueError(f"unknown name {name!r}; use a control {list(self.control_names)}, "
                         + (f"a field {list(self.fields)}, " if self.fields else "")
                         + "or None for the solution space")

    def field_space(self, name: str):
        """The collapsed function space of field ``name``."""
        if name not in self._field_spaces:
            raise ValueError(f"unknown field {name!r}; this problem's fields are {list(self.fields)}")
        return self._field_spaces[name]

    # ------------------------------------------------- derivative information
    def gradient_form(self, name: str):
        """Compiled linear form on control ``name``'s space whose assembly with
        ``u`` and ``lam`` set gives dJ/dm = -lam^T dF/dm (built on first use)."""
        self._check_name(name)
        if name not in self._gradient_forms:
            m = self._controls[name]
            residual = ufl.action(self.a, self.u) - self.L
            dF = expand_derivatives(ufl.derivative(residual, m, ufl.TrialFunction(m.function_space)))
            form = None if dF.empty() else _dolfinx.compile_form(
                -ufl.action(ufl.adjoint(dF), self.lam))
            self._gradient_forms[name] = form
        return self._gradient_forms[name]

    def rhs_matrix_form(self, name: str):
        """Compiled bilinear form C_m = dL/dm (test space V, trial space of m)
        for an affine right-hand-side control (BC rows not applied)."""
        if name not in self.affine_rhs_controls:
            raise ValueError(f"control {name!r} does not enter the right-hand side affinely; "
                             f"affine ones: {sorted(self.affine_rhs_controls)}")
        if name not in self._rhs_matrix_forms:
            self._rhs_matrix_forms[name] = _dolfinx.compile_form(self._rhs_derivatives[name])
        return self._rhs_matrix_forms[name]

    def matrix_inputs(self) -> tuple:
        """Coefficients and constants whose values the matrix depends on."""
        return tuple(self.a.coefficients()) + tuple(self.a.constants())

    def homogeneous_bcs(self) -> bool:
        """Whether every Dirichlet value is zero (then the RHS has no lifting term)."""
        values = [bc.g.x.array if hasattr(bc.g, "x") else np.asarray(bc.g.value) for bc in self.bcs]
        local = all(not np.any(v) for v in values)
        return self.V.mesh.comm.allreduce(local, op=_LAND)

    def rhs_inputs(self) -> tuple:
        """Coefficients and constants the right-hand side (with lifting) depends on."""
        return (tuple(self.L.coefficients()) + tuple(self.L.constants())
                + (self.matrix_inputs() if self.bcs else ()) + tuple(bc.g for bc in self.bcs))

    def rhs_matrix_inputs(self, name: str) -> tuple:
        form = self._rhs_derivatives[name]
        return tuple(form.coefficients()) + tuple(form.constants())

    # ----------------------------------------------------------------- helpers
    def _rhs_derivative(self, name: str) -> ufl.Form:
        m = self._controls[name]
        return expand_derivatives(ufl.derivative(self.L, m, ufl.TrialFunction(m.function_space)))

    def _depends_on_controls(self, form: ufl.Form) -> bool:
        coeffs = set(form.coefficients())
        return any(fn in coeffs for fn in self._controls.values())

    def _check_name(self, name: str) -> None:
        if name not in self._controls:
            raise ValueError(f"unknown control {name!r}; this problem's controls are {list(self.control_names)}")

    def __repr__(self) -> str:
        return (f"Problem(V={_dolfinx.element_family(self.V)} {_dolfinx.element_degree(self.V)}, n={self.output_size}, "
                f"controls={list(self.control_names)}, matrix_controls={sorted(self.matrix_controls)})")


def _validated_constants(constants: Mapping) -> dict:
    if not isinstance(constants, Mapping):
        raise TypeError(f"constants must be a mapping name -> dolfinx.fem.Constant, got {type(constants).__name__}")
    for name, value in constants.items():
        if not isinstance(name, str) or not isinstance(value, dolfinx.fem.Constant):
            raise TypeError(f"constants[{name!r}] must be a dolfinx.fem.Constant under a str name, "
                            f"got {type(value).__name__}")
    return dict(constants)


def _validated_controls(controls: Mapping, a: ufl.Form, L: ufl.Form, msh) -> dict:
    if not isinstance(controls, Mapping):
        raise TypeError(f"controls must be a mapping {{name: dolfinx.fem.Function}}, got {type(controls).__name__}")
    coefficients = set(a.coefficients()) | set(L.coefficients())
    out = {}
    for name, fn in controls.items():
        if not isinstance(name, str) or not name.isidentifier() or keyword.iskeyword(name):
            raise ValueError(f"control names must be Python identifiers (they become keyword "
                             f"arguments of the layer), got {name!r}")
        if not isinstance(fn, dolfinx.fem.Function):
            raise TypeError(f"controls[{name!r}] must be a dolfinx.fem.Function, got {type(fn).__name__}; "
                            "wrap constants in a Function on a DG0 or P1 space to control them")
        if fn.function_space.mesh is not msh:
            raise ValueError(f"controls[{name!r}] lives on a different mesh than the solution space; "
                             "create it on the same mesh object")
        if fn not in coefficients:
            raise ValueError(f"controls[{name!r}] does not appear in a or L; use the same Function "
                             "object when building the forms")
        out[name] = fn
    return out


def _owned_size(space) -> int:
    return space.dofmap.index_map.size_local * space.dofmap.index_map_bs


def _as_array(values, argname: str) -> np.ndarray:
    """A float64 numpy copy of a tensor (detached, on the CPU) or array-like."""
    if hasattr(values, "detach"):
        values = values.detach().cpu().numpy()
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{argname} must be a tensor or an array of numbers, got {type(values).__name__}") from None


def _describe_form(form) -> str:
    if isinstance(form, ufl.Form):
        return f"a form with {len(form.arguments())} argument(s)"
    return type(form).__name__

