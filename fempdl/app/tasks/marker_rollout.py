"""The marker inverse problem's physics: an initial velocity moves a passive marker, P(v0) -> m_T.

Enclosed incompressible flow (no-slip on the whole boundary) on an
unstructured mesh. A raw velocity g (the network's output, in the Taylor-Hood
velocity space V) is first made divergence-free and smooth by one
Helmholtz-Leray projection, then the flow and the marker advance ``steps``
implicit steps of size dt:

    v0 = Pi g:           find (v0, p) in V_0 x Q:  ∫ v0·v + ell^2 ∇v0:∇v - p div v - q div v0 dx = ∫ g·v dx,
    v_t = S(v_{t-1}):    one Oseen step linearised around v_{t-1} (:mod:`fempdl.forms.oseen`,
                         w = u_prev = v_{t-1}, viscosity ``nu``, SUPG),
    m_t = T(v_t, m_{t-1}): one marker step (:mod:`fempdl.forms.transport`, diffusivity
                         ``kappa``, SUPG),                                  t = 1..T.

Pi is the Oseen form with w = 0, dt = 1 and nu = ell^2 (``smoothing`` = ell):
linear, discretely divergence-free (∫ q div v0 = 0 for all pressures q), the
identity on discretely divergence-free fields when ell = 0, and a smoothing
of length ell otherwise; its kernel holds the gradient fields, so a prior
||g||^2 on the raw velocity is a smoothness prior ||v0||^2 + 2 ell^2 ||∇v0||^2
+ ... on v0. The marker's mass is conserved by every step.

Shapes: g (B, n_v) or (n_v,) with n_v = ``velocity_size`` (vector DOFs of V,
blocked per node); m0 (B, n_m) or (n_m,) with n_m = ``marker_size`` (P_k
DOFs); the output m_T (B, n_m). Every solve is a :class:`SolveLayer`, so the
rollout is differentiable end to end (exact gradients with converged solves,
the implicit gradient with capped ones), and ``max_it`` sets the cap of the
flow and marker solves at once (PRDP can drive it; the projection is always
converged).
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import torch
import ufl

from fempdl import forms
from fempdl.core import _dolfinx
from fempdl.core.checks import is_int, is_real
from fempdl.core.mesh import as_tagged
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.assembly import assemble_scipy
from fempdl.solve.options import KSPOptions

__all__ = ["ENCLOSED_LU", "MarkerFlow"]

# A direct solver for the enclosed flow's singular saddle point (the pressure
# constant spans its null space): MUMPS with null-pivot detection. Plain LU
# factorises the singular matrix without noticing and returns velocities that
# jump by orders of magnitude under 1e-6 changes of the advecting velocity.
ENCLOSED_LU = KSPOptions.preset("lu", petsc_options={"pc_factor_mat_solver_type": "mumps", "mat_mumps_icntl_24": 1})


class MarkerFlow(torch.nn.Module):
    """P(g, m0) -> m_T on an enclosed domain (module docstring).

    Args:
        msh: a :class:`fempdl.core.mesh.TaggedMesh` or dolfinx Mesh (2D or 3D).
        steps: number of time steps T (>= 1).
        dt: time step; nu: the fluid's viscosity; kappa: the marker's diffusivity.
        smoothing: the projection's smoothing length ell (> 0).
        degree: velocity degree k of Taylor-Hood P_k-P_(k-1) (>= 2).
        marker_degree: Lagrange degree of the marker.
        flow_options, transport_options: solvers of the flow and marker steps
            (:class:`KSPOptions` or a preset name; default :data:`ENCLOSED_LU`
            and LU). Capped presets
            for the saddle-point flow step: ``"schur"``; for the marker: ``"gmres-ilu"``.
    """

    def __init__(self, msh, *, steps: int = 4, dt: float = 0.1, nu: float = 1e-2, kappa: float = 1e-3,
                 smoothing: float = 0.05, degree: int = 2, marker_degree: int = 1,
                 flow_options: KSPOptions | str = ENCLOSED_LU, transport_options: KSPOptions | str = "lu"):
        super().__init__()
        if not is_int(steps) or steps < 1:
            raise ValueError(f"steps must be an int >= 1, got {steps!r}")
        if not is_real(smoothing) or not smoothing > 0:
            raise ValueError(f"smoothing must be a positive length (the projection's ell), got {smoothing!r}")
        tagged = as_tagged(msh)
        self.steps = int(steps)
        self.projection = forms.oseen.problem(tagged, controls=("u_prev",), nu=float(smoothing) ** 2, dt=1.0,
                                              degree=degree, supg=False)
        self.flow = forms.oseen.problem(tagged, controls=("w", "u_prev"), nu=nu, dt=dt, degree=degree)
        V = self.flow.field_space("u")
        if not np.array_equal(self.projection.field_space("u").tabulate_dof_coordinates(),
                              V.tabulate_dof_coordinates()):
            raise RuntimeError("the projection's and the flow's velocity spaces number their DOFs differently")
        self.transport = forms.transport.problem(tagged, controls=("w", "m_prev"), kappa=kappa, dt=dt,
                                                 degree=marker_degree, velocity_space=V)
        self.project_layer = SolveLayer(self.projection, ENCLOSED_LU)
        self.flow_layer = SolveLayer(self.flow, flow_options)
        self.transport_layer = SolveLayer(self.transport, transport_options)
        self.velocity_size = self.flow.control_size("u_prev")
        self.marker_size = self.transport.output_size
        self._masses: dict = {}

    # ------------------------------------------------------------ physics
    def initial_velocity(self, g: torch.Tensor) -> torch.Tensor:
        """v0 = Pi g: (B, n_v) or (n_v,), divergence-free with no-slip walls."""
        return self.projection.split(self.project_layer(u_prev=g))["u"]

    def forward(self, g: torch.Tensor, m0: torch.Tensor, *, trajectory: bool = False):
        """m_T (B, n_m) from the raw velocity g and the initial marker m0; with
        ``trajectory``, also the lists of velocities v_0..v_T and markers m_0..m_T."""
        v, m = self.initial_velocity(g), m0
        velocities, markers = [v], [m]
        for _ in range(self.steps):
            v = self.flow.split(self.flow_layer(w=v, u_prev=v))["u"]
            m = self.transport_layer(w=v, m_prev=m)
            velocities.append(v)
            markers.append(m)
        return (m, velocities, markers) if trajectory else m

    # ------------------------------------------------------------ solver caps (PRDP)
    @property
    def layers(self) -> tuple:
        """The capped layers (flow and marker steps) whose iterations a run counts."""
        return (self.flow_layer, self.transport_layer)

    @property
    def max_it(self) -> int | None:
        return self.flow_layer.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        for layer in self.layers:
            layer.max_it = value

    # ------------------------------------------------------------ norms
    def mass_matrix(self, which: str) -> sp.csr_matrix:
        """The mass matrix (scipy CSR) of the owned ``"velocity"`` or ``"marker"`` DOFs (serial)."""
        spaces = {"velocity": self.flow.field_space("u"), "marker": self.transport.V}
        if which not in spaces:
            raise ValueError(f"which must be one of {list(spaces)}, got {which!r}")
        if which not in self._masses:
            space = spaces[which]
            u, v = ufl.TrialFunction(space), ufl.TestFunction(space)
            n = space.dofmap.index_map.size_local * space.dofmap.index_map_bs
            self._masses[which] = sp.csr_matrix(assemble_scipy(_dolfinx.compile_form(ufl.inner(u, v) * ufl.dx))[:n, :n])
        return self._masses[which]

    def relative_error(self, which: str, values: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
        """||values - truth||_M / ||truth||_M per sample (B,): the relative L2 error of a
        ``"velocity"`` or ``"marker"`` (no graph)."""
        M = self.mass_matrix(which)
        e = (values - truth).detach().double().reshape(-1, M.shape[0]).numpy()
        t = truth.detach().double().reshape(-1, M.shape[0]).numpy()
        return torch.as_tensor(np.sqrt(np.einsum("bi,bi->b", e, (M @ e.T).T) / np.einsum("bi,bi->b", t, (M @ t.T).T)))

    def close(self) -> None:
        for layer in (self.project_layer, *self.layers):
            layer.close()
