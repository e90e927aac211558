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

from collections.abc import Mapping

import dolfinx.fem
import ufl
from ufl.algorithms import expand_derivatives

from fempdl.core import _dolfinx
from fempdl.core.pointwise_forms import (
    coefficients_of,
    pointwise_in,
    roots_in,
    total_derivative,
    with_pointwise_quadrature,
)
from fempdl.core.problem_base import ProblemBase, describe_form, validated_controls

__all__ = ["Problem"]


class Problem(ProblemBase):
    """A linear variational problem a(u, v) = L(v) with named controls.

    Args:
        a: bilinear UFL form (test function number 0, trial function number 1).
        L: linear UFL form on the same test space.
        bcs: Dirichlet conditions on the trial space (``dolfinx.fem.dirichletbc``): a list, or one.
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
            orthogonal to it (see :class:`fempdl.solve.capped_solver.CappedSolver`).
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
        symmetric: ``a`` is symmetric, a(u, v) = a(v, u), for every value of the
            controls (Poisson, elasticity, heat): A is then symmetric (Dirichlet rows
            and columns are replaced alike), its adjoint solve is its forward solve,
            and the ``"cholesky"`` preset may factorise it (about half LU's work).
            Checked on the assembled A before the first Cholesky factorisation.
        positive: names of controls and Constants whose values must be > 0 (a
            diffusivity, a Young's modulus, a time step): a layer call passing a
            value <= 0 for such a control, or made while such a Constant holds one,
            is refused with a ValueError before any solve (``problem.positive``,
            assignable; the bundled forms declare theirs).
        nonnegative: names of Constants whose values must be >= 0, checked alike
            (``problem.nonnegative``).
    """

    def __init__(self, a: ufl.Form, L: ufl.Form, bcs=(), controls: Mapping | None = None, *,
                 fields: Mapping[str, int] | None = None, nullspace=(), constants: Mapping | None = None,
                 near_nullspace=(), symmetric: bool = False, positive=(), nonnegative=()):
        if not isinstance(a, ufl.Form) or len(a.arguments()) != 2:
            raise TypeError(f"a must be a bilinear UFL form (two arguments), got {describe_form(a)}")
        if not isinstance(L, ufl.Form) or len(L.arguments()) != 1:
            raise TypeError(f"L must be a linear UFL form (one argument), got {describe_form(L)}")
        test, trial = sorted(a.arguments(), key=lambda arg: arg.number())
        if L.arguments()[0].ufl_function_space() != test.ufl_function_space():
            raise ValueError("L's test space differs from a's test space; build both with the same TestFunction")
        V = trial.ufl_function_space()
        a, L = with_pointwise_quadrature(a, "a"), with_pointwise_quadrature(L, "L")
        self.a = a
        self.L = L
        self._init_spaces(V, bcs, validated_controls(controls or {}, {"a": a, "L": L}, V.mesh), fields=fields,
                          nullspace=nullspace, near_nullspace=near_nullspace, constants=constants,
                          positive=positive, nonnegative=nonnegative, forms=(a, L))
        self.u = dolfinx.fem.Function(self.V, name="u")
        self.a_form = _dolfinx.compile_form(a)
        self.L_form = _dolfinx.compile_form(L)

        a_coeffs, L_coeffs = coefficients_of(a), coefficients_of(L)
        # A network's parameters are an input of the forms that hold it (a matrix "control" of a kappa_theta(x)).
        self.matrix_controls = frozenset([n for n, fn in self._controls.items() if fn in a_coeffs]
                                         + list(roots_in([a])))
        self.rhs_controls = frozenset([n for n, fn in self._controls.items() if fn in L_coeffs] + list(roots_in([L])))
        self._rhs_derivatives = {n: self._rhs_derivative(n) for n in self.rhs_controls if n in self._controls}
        self.affine_rhs_controls = frozenset(
            n for n, dL in self._rhs_derivatives.items()
            if n not in self.matrix_controls and not self._depends_on_controls(dL))
        # Matrix controls the matrix is affine in (A(m) = A0 + sum_k m_k A_k).
        # (The direction is a third argument: a already has a test and a trial function.)
        self.affine_matrix_controls = frozenset(
            n for n in self.matrix_controls if n in self._controls
            and not _reads_control(total_derivative(a, self._controls[n],
                                                    ufl.Argument(self._controls[n].function_space, 2)),
                                   self._controls[n]))
        if not isinstance(symmetric, bool):
            raise TypeError(f"symmetric must be a bool, got {type(symmetric).__name__}")
        self.symmetric = symmetric
        self._gradient_forms: dict = {}
        self._rhs_matrix_forms: dict = {}

    # ------------------------------------------------- derivative information
    def gradient_form(self, name: str):
        """Compiled linear form on control ``name``'s space whose assembly with
        ``u`` and ``lam`` set gives dJ/dm = -lam^T dF/dm (built on first use)."""
        self._check_name(name)
        if name not in self._gradient_forms:
            m = self._controls[name]
            dF = total_derivative(self._residual(), m, ufl.TrialFunction(m.function_space))
            form = None if dF.empty() else _dolfinx.compile_form(
                -ufl.action(ufl.adjoint(dF), self.lam))
            self._gradient_forms[name] = form
        return self._gradient_forms[name]

    def network_cotangent_forms(self, name: str) -> dict:
        """{alpha: compiled linear form} on the spaces of network ``name``'s values and derivatives:
        d/dN_alpha of -F(u, lam), F = a(u, .) - L, the cotangents whose vector-Jacobian product through the
        network is dJ/dtheta (:mod:`fempdl.core.pointwise_forms`)."""
        key = ("network", name)
        if key not in self._gradient_forms:
            test = self.a.arguments()[0] if self.a.arguments()[0].number() == 0 else self.a.arguments()[1]
            functional = -ufl.replace(self._residual(), {test: self.lam})
            self._gradient_forms[key] = {alpha: _dolfinx.compile_form(form) for alpha, form in
                                         self.networks[name].cotangent_forms(expand_derivatives(functional)).items()}
        return self._gradient_forms[key]

    def _residual(self) -> ufl.Form:
        return ufl.action(self.a, self.u) - self.L

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
        return total_derivative(self.L, m, ufl.TrialFunction(m.function_space))

    def _depends_on_controls(self, form: ufl.Form) -> bool:
        coeffs = coefficients_of(form)
        return bool(pointwise_in(form)) or any(fn in coeffs for fn in self._controls.values())

    def __repr__(self) -> str:
        return (f"Problem(V={_dolfinx.element_family(self.V)} {_dolfinx.element_degree(self.V)}, n={self.output_size}, "
                f"controls={list(self.control_names)}, matrix_controls={sorted(self.matrix_controls)})")


def _reads_control(form: ufl.Form, control) -> bool:
    """Whether ``form`` reads ``control``, directly or through a network's operands or values."""
    return bool(pointwise_in(form)) or control in coefficients_of(form)
