"""A nonlinear variational problem F(u; m) = 0 with named controls, and its derivative forms.

``NonlinearProblem(F, u, bcs, controls={name: Function})`` describes: find u in
V with u = g on the Dirichlet boundary and

    F(u, v; m) = 0   for all v in V0,

where ``F`` is a UFL form linear in the test function v and (nonlinear) in the
Function ``u``, and the controls m are DOLFINx Functions among its coefficients.
The Jacobian J(u; m) = dF/du is ``ufl.derivative(F, u, du)`` unless given.

Forms for the derivatives (all linear forms, assembled with the work Functions set):

* implicit gradient, at a solution u with the adjoint lam of (dF/du)(u)^T lam = dJ/du
  (BC entries zeroed; the exact dF/du even when a different J drives Newton):
  dJ/dm = -d/dm [F(u, lam; m)] (:meth:`gradient_form`);
* one Newton step u' = u - a * delta, J(u) delta = F(u), run backwards with
  mu = J(u)^{-T} u'_bar and Q(u, m) = mu^T J(u; m) delta - F(u, mu; m)
  (delta and mu held fixed): u_bar = u'_bar + a * dQ/du and m_bar += a * dQ/dm
  (:meth:`step_state_form`, :meth:`step_control_form`). With the exact Jacobian
  dF/du^T mu = u'_bar, and u_bar reduces to a * d/du [mu^T J(u) delta].

The module knows DOLFINx and UFL but nothing of torch or of solvers.
"""
from __future__ import annotations

from collections.abc import Mapping

import dolfinx.fem
import ufl
from ufl.algorithms import expand_derivatives

from fempdl.core import _dolfinx
from fempdl.core.pointwise_forms import coefficients_of, roots_in, total_derivative, with_pointwise_quadrature
from fempdl.core.problem_base import ProblemBase, describe_form, validated_controls

__all__ = ["NonlinearProblem"]


class NonlinearProblem(ProblemBase):
    """A nonlinear variational problem F(u, v; m) = 0 with named controls.

    Args:
        F: the residual, a UFL form with one argument (the test function) in which
            the Function ``u`` appears.
        u: the unknown, a ``dolfinx.fem.Function`` on the test function's space.
            Solves write each sample's solution into it (the layer's work state).
        bcs: Dirichlet conditions on u's space (``dolfinx.fem.dirichletbc``), a list or
            one; a solution takes their values on the boundary.
        controls: ``{name: dolfinx.fem.Function}`` among F's coefficients, on u's mesh.
        J: the Jacobian, a bilinear form (test, trial on u's space); default
            ``ufl.derivative(F, u, TrialFunction(V))``. A different J (e.g. a Picard
            linearisation) changes the Newton iteration, not its solution.

    Keyword Args:
        fields, nullspace, constants, near_nullspace, positive, nonnegative: as for :class:`fempdl.Problem`.

    Attributes:
        V, u, lam: the solution space, the unknown and the adjoint work Function.
        step: the work Function of a Newton step delta (unrolled derivatives).
        F_form, J_form: the compiled residual and Jacobian (the iteration's).
        exact_J_form: the compiled dF/du (the implicit gradient's; ``J_form`` unless J was given).
        jacobian_controls, exact_jacobian_controls: names of the controls J and dF/du depend on.
    """

    def __init__(self, F: ufl.Form, u: dolfinx.fem.Function, bcs=(), controls: Mapping | None = None,
                 J: ufl.Form | None = None, *, fields: Mapping[str, int] | None = None, nullspace=(),
                 constants: Mapping | None = None, near_nullspace=(), positive=(), nonnegative=()):
        if not isinstance(F, ufl.Form) or len(F.arguments()) != 1:
            raise TypeError(f"F must be a residual: a UFL form with one argument (the test function), "
                            f"got {describe_form(F)}")
        if not isinstance(u, dolfinx.fem.Function):
            raise TypeError(f"u must be the unknown dolfinx.fem.Function of F, got {type(u).__name__}")
        V = u.function_space
        if F.arguments()[0].ufl_function_space() != V:
            raise ValueError("F's test function lives on a different space than u; build the TestFunction on "
                             "u.function_space")
        F = with_pointwise_quadrature(F, "F")
        if u not in coefficients_of(F):
            raise ValueError("F is not a residual in u: u does not appear in F (a linear problem a(w, v) = L(v) "
                             "in a TrialFunction w is a fempdl.Problem)")
        # With a network N(u) in F, dF/du takes the chain rule through N's operands (fempdl.core.pointwise_forms).
        exact_J = total_derivative(F, u, ufl.TrialFunction(V))
        given_J = J is not None
        if J is None:
            J = exact_J
        elif not isinstance(J, ufl.Form) or len(J.arguments()) != 2:
            raise TypeError(f"J must be a bilinear UFL form (test and trial function), got {describe_form(J)}")
        elif any(arg.ufl_function_space() != V for arg in J.arguments()):
            raise ValueError("J's test and trial functions must live on u's space")
        else:
            J = with_pointwise_quadrature(J, "J")
        checked = validated_controls(controls or {}, {"F": F}, V.mesh)
        for name, fn in checked.items():
            if fn is u:
                raise ValueError(f"controls[{name!r}] is the unknown u itself; a control is an input of F")
        self.F, self.J = F, J
        self._init_spaces(V, bcs, checked, fields=fields, nullspace=nullspace, near_nullspace=near_nullspace,
                          constants=constants, positive=positive, nonnegative=nonnegative, forms=(F, J))
        self.u = u
        self.step = dolfinx.fem.Function(V, name="newton_step")
        self.F_form = _dolfinx.compile_form(F)
        self.J_form = _dolfinx.compile_form(J)
        # The implicit gradient needs dF/du whatever J the iteration uses (a Picard J changes the
        # iteration, not the solution): compiled apart only when J was given.
        self.exact_J_form = _dolfinx.compile_form(exact_J) if given_J else self.J_form
        self.jacobian_controls = _controls_in(J, checked)
        self.exact_jacobian_controls = _controls_in(exact_J, checked) if given_J else self.jacobian_controls
        self._test = F.arguments()[0]
        self._forms: dict = {}

    # ------------------------------------------------- derivative information
    def gradient_form(self, name: str):
        """Compiled linear form on control ``name``'s space: -d/dm F(u, lam; m), the
        implicit gradient with ``u`` (the solution) and ``lam`` (the adjoint) set;
        ``None`` if F does not depend on it."""
        self._check_name(name)
        return self._cached(("gradient", name), lambda: self._derivative(
            -ufl.replace(self.F, {self._test: self.lam}), self._controls[name]))

    def network_cotangent_forms(self, name: str, step: bool = False) -> dict:
        """{alpha: compiled linear form} on the spaces of network ``name``'s values and derivatives: d/dN_alpha
        of -F(u, lam) (the implicit gradient's cotangents), or with ``step`` of Q (one Newton step run
        backwards); their vector-Jacobian product through the network is the parameters' gradient."""
        functional = self._step_objective() if step else -ufl.replace(self.F, {self._test: self.lam})
        return self._cached(("network", name, step), lambda: {
            alpha: _dolfinx.compile_form(form)
            for alpha, form in self.networks[name].cotangent_forms(expand_derivatives(functional)).items()})

    def step_state_form(self):
        """Compiled linear form on V: dQ/du for one Newton step run backwards (module docstring),
        with ``u`` = u_k, ``step`` = delta_k and ``lam`` = mu_k set."""
        return self._cached("step_state", lambda: self._derivative(self._step_objective(), self.u))

    def step_control_form(self, name: str):
        """Compiled linear form on control ``name``'s space: dQ/dm for one Newton step run backwards."""
        self._check_name(name)
        return self._cached(("step_control", name), lambda: self._derivative(
            self._step_objective(), self._controls[name]))

    def _step_objective(self) -> ufl.Form:
        """Q = mu^T J(u; m) delta - F(u, mu; m), a functional (no arguments)."""
        test, trial = sorted(self.J.arguments(), key=lambda arg: arg.number())
        return (ufl.replace(self.J, {test: self.lam, trial: self.step})
                - ufl.replace(self.F, {self._test: self.lam}))

    def _derivative(self, functional: ufl.Form, wrt: dolfinx.fem.Function):
        form = total_derivative(functional, wrt, ufl.TestFunction(wrt.function_space))
        return None if form.empty() else _dolfinx.compile_form(form)

    def _cached(self, key, build):
        if key not in self._forms:
            self._forms[key] = build()
        return self._forms[key]

    def __repr__(self) -> str:
        return (f"NonlinearProblem(V={_dolfinx.element_family(self.V)} {_dolfinx.element_degree(self.V)}, "
                f"n={self.output_size}, controls={list(self.control_names)})")


def _controls_in(form: ufl.Form, controls: Mapping) -> frozenset:
    """Names of the ``controls`` among the coefficients of ``form`` once its derivatives are expanded."""
    form = expand_derivatives(form)
    coefficients = coefficients_of(form)
    return frozenset([name for name, fn in controls.items() if fn in coefficients] + list(roots_in([form])))

