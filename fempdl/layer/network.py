"""A torch network as a coefficient of a UFL form, evaluated at the quadrature points.

``N = Network(module, operands=(u,), name="kappa")`` is a DOLFINx Function on a quadrature space
(:class:`~fempdl.core.pointwise.PointwiseCoefficient`) that forms use like any coefficient::

    F = inner(N * grad(u), grad(v)) * dx - f * v * dx

At every assembly the operands (the unknown, its gradient, x, other coefficients) are evaluated at the
quadrature points of this rank's cells and ``module(*operands)`` runs once on all of them, each operand
as a (P, size_i) tensor, returning (P,) or (P, size) values (P, *shape) for N's ``shape``. The
derivatives with respect to the operands that a Jacobian needs are ``torch.func`` Jacobians of the
module at one point, vmapped over the points (so the module must treat points independently: no
batch statistics). The gradient with respect to the module's parameters is one ``torch.func.vjp``
through those values with the adjoint-weighted residual derivatives as cotangents
(:meth:`fempdl.solve.control_forms.ControlForms.network_gradient`).

The module is evaluated in float64 on the CPU whatever its parameters' dtype: the parameters are cast
(a float32 module's gradient comes back in float32), so Newton's tolerances and the Jacobian's
exactness are those of float64 physics. A layer passes the parameters of every network its problem
holds as call inputs, by value: a backward uses the weights its forward read.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch.func import functional_call, jacrev, vjp, vmap

from fempdl.core.pointwise import PointwiseCoefficient
from fempdl.core.problem_base import as_array

__all__ = ["Network"]


class Network(PointwiseCoefficient):
    """A ``torch.nn.Module`` inside the weak form (module docstring).

    Args:
        module: maps operand tensors (P, size_i), one per operand, to (P,) or (P, *shape) values.
        operands: UFL expressions of one mesh: ``(u,)``, ``(u, grad(u))``, ``(ufl.SpatialCoordinate(msh),)``,
            ``(I + grad(u),)``; a tensor operand is passed flattened row by row.
        shape: the value shape, ``()`` (a conductivity), ``(m,)`` or ``(a, b)`` (a stress).
        degree: the quadrature degree of its points and of the integrals that hold it (default twice the
            highest degree among the operands' elements).
        name: the network's name in errors and the layer's name for its parameters (unique per problem).
        positive: refuse values <= 0 at any point (a conductivity, a viscosity).
    """

    kind = "network"

    def __init__(self, module: torch.nn.Module, operands, *, shape: tuple = (), degree: int | None = None,
                 name: str = "network", positive: bool = False):
        if not isinstance(module, torch.nn.Module):
            raise TypeError(f"module must be a torch.nn.Module, got {type(module).__name__}; wrap a function "
                            "of tensors in a Module whose forward calls it")
        if not isinstance(name, str) or not name.isidentifier():
            raise ValueError(f"name must be a Python identifier (the layer's name for the parameters), got {name!r}")
        self.module = module
        self._names = [n for n, _ in module.named_parameters()]
        self._shapes = [p.shape for _, p in module.named_parameters()]
        super().__init__(operands, shape=shape, degree=degree, name=name, positive=positive)
        self._theta = self.parameters_tensor().detach().to(torch.float64).numpy().copy()

    def field_at(self, problem, state):
        """N at the state ``state`` (one sample's owned DOF values of ``problem``'s unknown, a tensor or an
        array) with the module's current weights, as a DG0 Function of cell averages (XDMF-ready:
        ``fempdl.io.write_xdmf(path, {"kappa": N.field_at(prob, u[0])})``)."""
        assembly_state = problem.u.x.array.copy()
        problem.u.x.array[:problem.output_size] = as_array(state, "state")
        problem.u.x.scatter_forward()
        saved = self._theta
        self.set_parameters(self.parameters_tensor().detach().to(torch.float64).numpy())
        try:
            self.refresh()
            return self.cell_average()
        finally:
            problem.u.x.array[:] = assembly_state
            self._theta = saved

    # ----------------------------------------------------------- parameters
    @property
    def parameter_count(self) -> int:
        return sum(math.prod(s) for s in self._shapes)

    def parameters_tensor(self) -> torch.Tensor:
        """The module's parameters as one flat (parameter_count,) tensor, differentiable into them."""
        params = list(self.module.parameters())
        if not params:
            return torch.zeros(0, dtype=torch.float64)
        return torch.cat([p.reshape(-1) for p in params])

    def parameter_values(self) -> np.ndarray:
        return self._theta

    def set_parameters(self, values: np.ndarray) -> None:
        self._theta = np.array(values, dtype=np.float64)

    def _unflatten(self, theta: torch.Tensor) -> dict:
        chunks = torch.split(theta, [math.prod(s) for s in self._shapes]) if self._shapes else ()
        return {n: c.reshape(s) for n, c, s in zip(self._names, chunks, self._shapes)}

    # --------------------------------------------------------------- values
    def values_at(self, operands: list[np.ndarray], alphas: tuple) -> dict:
        ops = [torch.from_numpy(np.ascontiguousarray(o)) for o in operands]
        with torch.no_grad():
            values = self._evaluate(torch.from_numpy(self._theta), ops, alphas)
        return {alpha: v.numpy() for alpha, v in zip(alphas, values)}

    def parameter_vjp(self, operands: list[np.ndarray], cotangents: dict) -> np.ndarray:
        if not self.parameter_count:
            return np.zeros(0)
        ops = [torch.from_numpy(np.ascontiguousarray(o)) for o in operands]
        alphas = tuple(cotangents)
        # torch.func, not torch.autograd: this runs inside the layer's adjoint operator, below autograd.
        _, pullback = vjp(lambda theta: tuple(self._evaluate(theta, ops, alphas)), torch.from_numpy(self._theta))
        (grad,) = pullback(tuple(torch.from_numpy(np.ascontiguousarray(cotangents[a])) for a in alphas))
        return grad.numpy()

    def _evaluate(self, theta: torch.Tensor, ops: list[torch.Tensor], alphas: tuple) -> list[torch.Tensor]:
        """[(P, size_alpha) values of N_alpha] for ``alphas``. A scalar N's first derivatives come from one
        vector-Jacobian product of the batched module with ones (the points are independent, so the gradient
        of the sum is each point's); other derivatives from vmapped per-point Jacobians."""
        params = self._unflatten(theta)
        points = ops[0].shape[0]

        def batched(*xs):
            return self._checked(functional_call(self.module, params, xs), points)
        first = [i for i in range(len(ops)) if (i,) in alphas] if not self.value_shape else []
        if first:
            values, pullback = vjp(lambda *xs: batched(*[xs[first.index(i)] if i in first else o
                                                         for i, o in enumerate(ops)]), *[ops[i] for i in first])
            grads = dict(zip(first, pullback(torch.ones_like(values))))
        else:
            values, grads = batched(*ops), {}
        out = []
        for alpha in alphas:
            if not alpha:
                out.append(values)
            elif len(alpha) == 1 and alpha[0] in grads:
                out.append(grads[alpha[0]].reshape(points, -1))
            else:
                f = self._at_point(params)
                for i in alpha:
                    f = jacrev(f, argnums=i)
                out.append(vmap(f)(*ops).reshape(points, -1))
        return out

    def _at_point(self, params: dict):
        """N at one point: operands (size_i,) -> N's shape."""
        def f(*ops):
            return self._checked(functional_call(self.module, params, tuple(o[None] for o in ops)), 1).reshape(
                self.value_shape)
        return f

    def _checked(self, values, points: int) -> torch.Tensor:
        size = math.prod(self.value_shape)
        if not isinstance(values, torch.Tensor):
            raise TypeError(f"network {self.name!r} returned {type(values).__name__}; its module must return a "
                            "tensor")
        accepted = {(points, *self.value_shape), (points, size)} | ({(points,)} if size == 1 else set())
        if tuple(values.shape) not in accepted:
            raise ValueError(f"network {self.name!r} returned shape {tuple(values.shape)} for {points} quadrature "
                             f"point(s); with shape={self.value_shape} it must return "
                             + " or ".join(str(s) for s in sorted(accepted, key=len)))
        return values.to(torch.float64).reshape(points, size)
