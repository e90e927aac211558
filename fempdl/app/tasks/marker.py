"""The sip-flow task: a network infers the initial velocity of an enclosed flow from the marker it moved.

Data (drawn from ``[data] seed``): per sample a raw velocity g, a sum of
``[data] modes`` smooth sine modes per component scaled so that the initial
velocity v0 = Pi g (:class:`fempdl.app.tasks.marker_rollout.MarkerFlow`: divergence-free,
no-slip) has the largest speed ``[marker] speed``; an initial marker m0, a
Gaussian blob of standard deviation ``[marker] width`` centred at a random node
at least ``width`` from the walls (``shape = "blob"``), or a Gaussian band of
that half-width through such a node in a random direction (``"band"``); with
``placement = "central"`` every marker is centred at the node farthest from
the walls (only the velocity varies); and the
observation y = m_T = P(g, m0) after ``[marker] steps`` steps of ``[pde] dt``.

The network (an MLP, ``[network]``) maps (m0, m_T), (B, 2 n_m), to a raw
velocity x (B, n_v); the physics projects it, so only Pi x matters. With
``[marker] inputs = "standardized"`` (the default) a
:class:`fempdl.app.tasks.networks.Standardize` built from the task's initial training
draw centres and scales the inputs first: raw marker values share a large
common mode, and both methods then learn far slower (docs/sip-hig.md, sip-flow). Training:

* ``"sip"``: proxy loss 1/2 ||x - stopgrad(x*)||^2 (mean over samples), x*
  from one damped Gauss-Newton step of :class:`fempdl.methods.sip.LinearisedGaussNewton`
  on the rollout (``[sip] cg_iterations``, ``damping``, ``eta``; Tikhonov
  prior ``[marker] prior`` on x, a smoothness prior on v0 through Pi);
* ``"backprop"``: Adam on 1/2 ||P(x, m0) - y||^2 (mean over samples), the
  gradient backpropagated through every solve of the rollout.

Validation metric (x space): the relative L2 error of the inferred initial
velocity, ||Pi x - v0||_M / ||v0||_M, mean over held-out samples;
:meth:`MarkerInversionTask.marker_errors` gives the y-space error
||P(x, m0) - y||_M / ||y||_M.
"""
from __future__ import annotations

import dataclasses

from mpi4py import MPI
import numpy as np
import torch
from scipy.spatial import cKDTree

from fempdl.app.schema import Scene
from fempdl.app.tasks.base import Task, make_optimizer, uncounted
from fempdl.app.tasks.data import smooth_fields
from fempdl.app.tasks.learned_inverse import SIP_SPEC
from fempdl.app.tasks.marker_rollout import MarkerFlow
from fempdl.app.tasks.networks import Standardize, mlp
from fempdl.core import _dolfinx, mesh
from fempdl.forms._common import make_function
from fempdl.methods.sip import LinearisedGaussNewton, proxy_loss

__all__ = ["MarkerInversionTask", "marker_flow"]


def marker_flow(scene: Scene) -> MarkerFlow:
    """The scene's physics on its mesh (serial, converged solves)."""
    pde, marker = scene.pde, scene.marker
    msh = mesh.load(scene.mesh.name, MPI.COMM_SELF, h=scene.mesh.h)
    return MarkerFlow(msh, steps=marker.steps, dt=pde.dt, nu=pde.nu, kappa=pde.kappa,
                      smoothing=marker.smoothing, degree=pde.degree)


def _blob(coords, centre, direction, width):
    return np.exp(-np.sum((coords[:, :2] - centre) ** 2, axis=1) / (2 * width ** 2))


def _band(coords, centre, direction, width):
    return np.exp(-((coords[:, :2] - centre) @ direction) ** 2 / (2 * width ** 2))


MARKER_SHAPES = {"blob": _blob, "band": _band}


class MarkerInversionTask(Task):
    """Infer v0 from (m0, m_T), trained by ``method`` ("sip" or "backprop"); module docstring."""

    specs = (dataclasses.replace(SIP_SPEC, pdes=("marker",)),)

    def __init__(self, scene: Scene, method: str):
        if scene.task != "sip" or scene.pde.type != "marker":
            raise ValueError(f"MarkerInversionTask trains sip scenes on the marker PDE, got a {scene.task} scene on "
                             f"{scene.pde.type!r}")
        if method not in ("sip", "backprop"):
            raise ValueError(f"a sip scene trains with method 'sip' or its baseline 'backprop', got {method!r}")
        self.scene, self.method = scene, method
        self.physics = marker_flow(scene)
        self.layers = list(self.physics.layers)
        data = scene.data
        self.train_size, self.val_size = data.train, data.validation
        self._centres = self._interior_nodes(scene.marker.width, scene.marker.placement)
        self.val = self._samples(self.val_size, np.random.default_rng([data.seed, 1]))
        self.train = self._samples(self.train_size, np.random.default_rng([data.seed, 0]))
        torch.manual_seed(data.seed)
        n_m, n_v = self.physics.marker_size, self.physics.velocity_size
        net = scene.network
        self.model = mlp(2 * n_m, n_v, net.hidden, net.layers, torch.nn.Tanh).double()
        if scene.marker.inputs == "standardized":
            self.model = torch.nn.Sequential(Standardize(self.train["inputs"]), self.model)
        if method == "backprop":
            self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), "adam",
                                                            scene.baseline.lr, scene.baseline.decay)
        else:
            self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                            scene.optimizer.lr, scene.optimizer.decay)
            spec = scene.sip
            self.inverse = LinearisedGaussNewton(self.physics, damping=spec.damping, prior=scene.marker.prior,
                                                 max_it=spec.cg_iterations, eta=spec.eta)

    # ------------------------------------------------------------ data
    def _interior_nodes(self, margin: float, placement: str) -> np.ndarray:
        """Marker node coordinates (x, y) at least ``margin`` from the boundary (all nodes if none is);
        for ``placement = "central"`` only the node farthest from it."""
        coords = self.physics.transport.dof_coordinates()[:, :2]
        V = self.physics.transport.V
        walls = _dolfinx.dirichlet_bc(V, make_function(V, 0.0, "walls"), _dolfinx.boundary_facets(V.mesh))
        wall = _dolfinx.bc_dofs_owned((walls,), len(coords))
        distance, _ = cKDTree(coords[wall]).query(coords)
        if placement == "central":
            return coords[[int(np.argmax(distance))]]
        inside = coords[distance >= margin]
        return inside if len(inside) else coords

    def _samples(self, count: int, rng: np.random.Generator) -> dict:
        """``count`` truths: raw velocities g, v0 = Pi g, markers m0 and observations y = P(g, m0)."""
        P, marker = self.physics, self.scene.marker
        g = torch.as_tensor(smooth_fields(P.flow.dof_coordinates("u_prev"), count, self.scene.data.modes, rng,
                                          components=2))
        with torch.no_grad():
            speed = P.initial_velocity(g).reshape(count, -1, 2).norm(dim=-1).max(dim=1).values
            g = g * (marker.speed / speed)[:, None]
            v0 = P.initial_velocity(g)
        coords = P.transport.dof_coordinates()
        shape = MARKER_SHAPES[marker.shape]
        m0 = []
        for _ in range(count):
            centre = self._centres[rng.integers(len(self._centres))]
            angle = rng.uniform(0.0, np.pi)
            m0.append(shape(coords, centre, np.array([np.cos(angle), np.sin(angle)]), marker.width))
        m0 = torch.as_tensor(np.array(m0))
        with torch.no_grad(), uncounted(P.layers):        # the data's rollouts are not training's solves
            y = P(g, m0)
        return {"g": g, "v0": v0, "m0": m0, "y": y, "inputs": torch.cat([m0, y], dim=-1)}

    def start_epoch(self, epoch: int) -> None:
        """With ``[data] resample``: new training truths, seeded by the epoch (the same on a resumed run)."""
        if self.scene.data.resample:
            self.train = self._samples(self.train_size, np.random.default_rng([self.scene.data.seed, 2, epoch]))

    # ------------------------------------------------------------ training
    def loss(self, idx) -> torch.Tensor:
        """The method's training loss on the samples ``idx``, a mean over them."""
        m0, y = self.train["m0"][idx], self.train["y"][idx]
        x = self.model(self.train["inputs"][idx])
        if self.method == "sip":
            return proxy_loss(x, self.inverse(x.detach(), y, m0=m0)) / len(idx)
        return 0.5 * ((self.physics(x, m0) - y) ** 2).sum(-1).mean()

    def validation_errors(self, idx) -> torch.Tensor:
        """Relative L2 error of the inferred initial velocity, per held-out sample (x space)."""
        with torch.no_grad():
            v0 = self.physics.initial_velocity(self.model(self.val["inputs"][idx]))
        return self.physics.relative_error("velocity", v0, self.val["v0"][idx])

    def marker_errors(self, idx) -> torch.Tensor:
        """Relative L2 error of the marker the inferred velocity moves, per held-out sample (y space)."""
        with torch.no_grad(), uncounted(self.layers):
            m_T = self.physics(self.model(self.val["inputs"][idx]), self.val["m0"][idx])
        return self.physics.relative_error("marker", m_T, self.val["y"][idx])

    def close(self) -> None:
        self.physics.close()
