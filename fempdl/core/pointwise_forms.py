"""The forms that hold pointwise coefficients (networks): which ones they hold, what they read, their
derivatives by the chain rule through the operands, and the quadrature degree of their integrals.

See :mod:`fempdl.core.pointwise` for the coefficients themselves. For a form F that holds N(o_1, ..., o_k),

    dF[c; dc] = dF/dc[dc] + dF/dN[ sum_i N_(i) . do_i/dc[dc] ]       (:func:`total_derivative`),

and every integral that holds N is integrated at N's points (:func:`with_pointwise_quadrature`).

The module knows DOLFINx and UFL but nothing of torch or of solvers.
"""
from __future__ import annotations

from collections.abc import Iterable

import dolfinx.fem
import numpy as np
import ufl
from ufl.algorithms import expand_derivatives
from ufl.constantvalue import Zero

from fempdl.core.pointwise import PointwiseFunction, operand_functions

__all__ = ["derivative", "total_derivative", "with_pointwise_quadrature", "pointwise_in", "coefficients_of",
           "roots_in", "reads_of"]


def pointwise_in(form) -> list[PointwiseFunction]:
    """The pointwise Functions (coefficients and derivatives) a form or an expression holds."""
    coefficients = form.coefficients() if isinstance(form, ufl.Form) else ufl.algorithms.extract_coefficients(form)
    return [c for c in coefficients if isinstance(c, PointwiseFunction)]


def roots_in(forms: Iterable) -> dict:
    """{name: PointwiseCoefficient} of the pointwise coefficients the forms hold (directly or by a derivative);
    two different ones under one name are refused."""
    roots: dict = {}
    for form in forms:
        for fn in pointwise_in(form):
            other = roots.setdefault(fn.root.name, fn.root)
            if other is not fn.root:
                raise ValueError(f"two pointwise coefficients (networks) are named {fn.root.name!r}; give each "
                                 "its own name=")
    return roots


def coefficients_of(form) -> set:
    """The coefficients a form reads: its own and, through each pointwise coefficient, its operands'."""
    found = set(form.coefficients())
    for fn in pointwise_in(form):
        found |= set(operand_functions(fn.root.operands))
    return found


def reads_of(form) -> list:
    """The Functions and Constants a form's values depend on, pointwise coefficients replaced by their
    operands' (which a call record captures: the pointwise values are recomputed from them)."""
    found = [c for c in form.coefficients() if not isinstance(c, PointwiseFunction)] + list(form.constants())
    for fn in pointwise_in(form):
        found += fn.root._reads
    return found


def total_derivative(form: ufl.Form, coefficient, direction) -> ufl.Form:
    """dF[c; dc] with the chain rule through every pointwise coefficient F holds (module docstring);
    derivatives expanded. ``coefficient`` a Function, ``direction`` an Argument (or Function) on its space."""
    result = expand_derivatives(ufl.derivative(form, coefficient, direction))
    for fn in pointwise_in(form):
        root, terms = fn.root, []
        for i, op in enumerate(root.operands):
            d_op = expand_derivatives(ufl.derivative(op, coefficient, direction))
            if isinstance(d_op, Zero):
                continue
            terms.append(_contract(root.derivative(fn.alpha + (i,)), d_op))
        if not terms:
            continue
        chain = sum(terms[1:], terms[0])
        placeholder = dolfinx.fem.Function(fn.function_space)
        along = expand_derivatives(ufl.derivative(form, fn, placeholder))
        if along.empty():
            continue
        flat = (chain if fn.ufl_shape == chain.ufl_shape
                else ufl.as_vector([chain[idx] for idx in np.ndindex(chain.ufl_shape)]))
        result = result + ufl.replace(along, {placeholder: flat})
    return result


def derivative(form: ufl.Form, coefficient, direction=None) -> ufl.Form:
    """``ufl.derivative`` through the networks a form holds: the residual of an energy with a network,
    ``F = fempdl.derivative(psi_theta(F(u)) * dx, u, v)``, holds d psi/dF at the points (UFL alone would
    give zero: it sees a network as an independent coefficient). Same arguments as ``ufl.derivative``
    (``direction`` default: a TestFunction, or a TrialFunction for a form that has one already)."""
    if direction is None:
        space = coefficient.function_space
        direction = ufl.TestFunction(space) if not form.arguments() else ufl.TrialFunction(space)
    return total_derivative(with_pointwise_quadrature(form, "the form"), coefficient, direction)


def _contract(derivative, d_op):
    """D . d_op over d_op's indices: D has shape S + d_op's shape."""
    rank = len(d_op.ufl_shape)
    if rank == 0:
        return derivative * d_op
    lead = derivative.ufl_shape[:len(derivative.ufl_shape) - rank]
    i, j = ufl.indices(len(lead)), ufl.indices(rank)
    expr = derivative[(*i, *j)] * d_op[j]
    return ufl.as_tensor(expr, i) if i else expr


def with_pointwise_quadrature(form: ufl.Form, what: str) -> ufl.Form:
    """``form`` with each integral that holds a pointwise coefficient integrated at its degree (refused: an
    integral over facets, two degrees in one integral, or another degree the user set)."""
    integrals, changed = [], False
    for itg in form.integrals():
        found = pointwise_in(itg.integrand())
        degrees = {fn.root.degree for fn in found}
        if not degrees:
            integrals.append(itg)
            continue
        names = sorted({fn.root.name for fn in found})
        if itg.integral_type() != "cell":
            raise ValueError(f"{what} holds pointwise coefficient(s) {names} in a {itg.integral_type()} integral; "
                             "a network is evaluated at the cells' quadrature points: use it in dx integrals only")
        if len(degrees) > 1:
            raise ValueError(f"{what} holds pointwise coefficients {names} of different degrees {sorted(degrees)} "
                             "in one integral; give them one degree=")
        degree = degrees.pop()
        given = itg.metadata().get("quadrature_degree")
        if given is not None and given != degree:
            raise ValueError(f"{what} integrates {names} with quadrature_degree={given}, but their values are held "
                             f"at the points of degree {degree}; drop the metadata or build the network with "
                             f"degree={given}")
        integrals.append(itg.reconstruct(metadata={**itg.metadata(), "quadrature_degree": degree}))
        changed = True
    return ufl.Form(integrals) if changed else form
