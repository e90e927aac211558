"""SIP's exact inverse for a Newton layer whose residual is affine in the control: no PDE solve.

The nonlinear counterpart of :class:`fempdl.methods.sip.ExactLinearInverse`, used by the sip task
on the nonlinear Poisson problem (infer the source f of -div(kappa (1 + alpha u^2) grad u) = f).
Shapes: x0 is (B, n_x) (the control's DOFs), y* is (B, n_y) (the layer's output DOFs).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse.linalg as spla
import torch
import ufl
from ufl.algorithms import expand_derivatives

from fempdl.core import _dolfinx
from fempdl.methods.sip import _LayerInverse
from fempdl.solve.assembly import assemble_scipy, set_owned

__all__ = ["ExactNonlinearInverse"]


class ExactNonlinearInverse(_LayerInverse):
    """x* = x0 + eta (P^{-1}(y*) - x0) for a nonlinear problem whose residual is affine in the control.

    For F(u; m) = N(u) - C m (the source f of nonlinear diffusion: N(u)_i =
    int kappa (1 + alpha u^2) grad u . grad phi_i, C = M the mass matrix) the
    discrete map is inverted exactly, without a PDE solve: on the DOFs off the
    Dirichlet boundary (f), C_ff m_f = N(y*)_f - C_fb m_b, with N(y*) = F(y*; 0)
    assembled without boundary conditions at u = y* and the boundary values m_b
    of x0 kept (y* does not determine them). So P(x*) = y* for eta = 1, to the
    precision of the solves that made y*. One residual assembly per sample and
    a solve with C_ff, factorised once. Serial; the layer is a
    :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` (only its problem is used).

    ``fixed``: values of the problem's other controls, (n_m,) each (shared by the batch).
    """

    def __init__(self, layer, control: str, eta: float = 1.0, fixed: dict | None = None):
        super().__init__(layer, control, fixed)
        problem = layer.problem
        if problem.V.mesh.comm.size > 1:
            raise ValueError("ExactNonlinearInverse assembles serial scipy operators; run it on one process")
        if not hasattr(problem, "F"):
            raise TypeError("ExactNonlinearInverse inverts a NonlinearProblem (a Newton layer); for a linear "
                            "fempdl.Problem use ExactLinearInverse")
        fn = problem.control(control)
        if fn.function_space != problem.V:
            raise ValueError(f"ExactNonlinearInverse needs the control on the solution space; {control!r} is not")
        batched = sorted(name for name, value in self.fixed.items() if torch.as_tensor(value).ndim != 1)
        if batched:
            raise ValueError(f"ExactNonlinearInverse takes fixed controls shared by the batch, (n_m,) each; "
                             f"{batched} are not")
        control_form = expand_derivatives(-ufl.derivative(problem.F, fn, ufl.TrialFunction(fn.function_space)))
        depends = set(control_form.coefficients()) & {fn, problem.u}
        if control_form.empty() or depends:
            raise ValueError(f"ExactNonlinearInverse needs a residual affine in {control!r}, F(u; m) = N(u) - C m "
                             "with C independent of u and m; this one is not (use LinearisedGaussNewton)")
        self.eta = float(eta)
        C = assemble_scipy(_dolfinx.compile_form(control_form))
        boundary = np.asarray(problem.bc_dofs)
        self._boundary_columns = C[self.free][:, boundary]
        self._solve_control_matrix = spla.factorized(C[self.free][:, self.free].tocsc())
        self._residual = _dolfinx.create_vector(problem.F_form)

    def operator(self, y: np.ndarray) -> np.ndarray:
        """N(y) = F(y; 0), assembled without boundary conditions (owned DOF values)."""
        p = self.layer.problem
        n = p.output_size
        for name, value in self.fixed.items():
            set_owned(p.control(name), torch.as_tensor(value).double().numpy(), p.control_size(name))
        set_owned(p.control(self.control), np.zeros(p.control_size(self.control)), p.control_size(self.control))
        set_owned(p.u, y, n)
        _dolfinx.assemble_vector_into(self._residual, p.F_form)
        return self._residual.getArray(readonly=True)[:n].copy()

    def inverse(self, y: np.ndarray, boundary_values: np.ndarray) -> np.ndarray:
        """The control m with P(m) = y (off the boundary), given its values at the Dirichlet DOFs."""
        m = np.zeros(self.layer.problem.control_size(self.control))
        m[self.layer.problem.bc_dofs] = boundary_values
        free_rhs = self.operator(y)[self.free] - self._boundary_columns @ boundary_values
        m[self.free] = self._solve_control_matrix(free_rhs)
        return m

    def __call__(self, x0: torch.Tensor, y_target: torch.Tensor) -> torch.Tensor:
        x0d = x0.detach().double()
        y = y_target.detach().double().numpy()
        boundary = self.layer.problem.bc_dofs
        exact = np.stack([self.inverse(y_i, x_i[boundary]) for y_i, x_i in zip(y, x0d.numpy())])
        return (x0d + self.eta * (torch.as_tensor(exact) - x0d)).to(x0.dtype)
