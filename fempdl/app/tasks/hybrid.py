"""The neural-hybrid flow corrector (Um et al.'s solver-in-the-loop) on FEM meshes.

A coarse-mesh Navier-Stokes stepper, each step one Oseen solve linearised
around the current velocity (w = u_prev = u_t, :mod:`fempdl.forms.oseen`),
is followed by a learned correction of the velocity:

    u*_{t+1} = S_K(w=u_t, u_prev=u_t)[u],     u_{t+1} = u*_{t+1} + mask * N(u*_{t+1}),

where S_K is the capped Schur-GMRES solve (K moved by PRDP; every step of the
unrolled chain calls the same layer, so PRDP refines all of them) and the mask
keeps the correction off the Dirichlet DOFs. The network's output layer starts
at zero, so the untrained hybrid is the coarse solver alone.

Training data: flow past the cylinder (the bundled ``obstacle`` channel;
parabolic inflow of peak ``[pde] inflow`` on "inlet", no-slip "walls" and
"obstacle", do-nothing "outlet"). On a fine mesh (``[hybrid] fine_h``) the flow
starts from rest and runs ``spinup`` converged steps; every sample then adds
its own smooth random perturbation (amplitude ``perturbation * inflow``) and
runs ``max(steps, rollout)`` converged (LU) fine steps. The fine states are
transferred to the coarse velocity DOFs by **point evaluation** of the fine P2
field at the coarse DOF coordinates (the fine mesh's cell containing each
point); coarse boundary nodes that the fine mesh does not contain (the chords
of the coarse cylinder polygon lie inside the finer polygon's hole) take the
nearest fine DOF's value, which is the no-slip value there.

Loss: the mean over the ``steps`` unrolled steps of the nMSE against the
transferred fine reference. Validation: the same chain over ``rollout`` steps
from held-out states with the *converged* coarse solver (LU) in place of the
capped one, so every K is judged alike.
"""
from __future__ import annotations

import functools

from mpi4py import MPI
import dolfinx.fem
import numpy as np
import torch
from scipy.spatial import cKDTree

from fempdl import forms
from fempdl.app.schema import PdeConfig, Scene, TaskSpec
from fempdl.app.tasks.base import Task, make_optimizer
from fempdl.app.tasks.data import smooth_fields
from fempdl.app.tasks.metrics import sample_nmse
from fempdl.app.tasks.networks import ResidualMLP
from fempdl.core import _dolfinx, mesh
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.options import KSPOptions

__all__ = ["HybridTask", "channel_problem", "VelocityTransfer"]


def channel_problem(tagged, pde: PdeConfig, controls=("w", "u_prev")):
    """The Oseen step on a channel mesh with inlet/walls/obstacle/outlet tags."""
    coords = tagged.mesh.geometry.x
    y0, y1 = float(coords[:, 1].min()), float(coords[:, 1].max())
    height, peak = y1 - y0, pde.inflow

    def inflow(x):
        s = (x[1] - y0) / height
        return np.stack([4.0 * peak * s * (1.0 - s), np.zeros_like(x[0])])

    return forms.oseen.problem(tagged, controls=controls, nu=pde.nu, dt=pde.dt, degree=pde.degree,
                               velocity={"inlet": inflow, "walls": 0.0, "obstacle": 0.0})


class VelocityTransfer:
    """Point evaluation of a velocity field on one mesh at the velocity DOFs of another.

    Args:
        source_space, target_space: collapsed vector Lagrange spaces (blocked DOFs).

    ``__call__(values)`` maps (B, n_source) owned DOF values to (B, n_target).
    """

    def __init__(self, source_space, target_space):
        self.n_source = source_space.dofmap.index_map.size_local * source_space.dofmap.index_map_bs
        self.bs = target_space.dofmap.index_map_bs
        n_nodes = target_space.dofmap.index_map.size_local
        points = target_space.tabulate_dof_coordinates()[:n_nodes]
        self.found, self.cells = _dolfinx.point_evaluator(source_space.mesh, points)
        missing = np.setdiff1d(np.arange(n_nodes), self.found)
        source_points = source_space.tabulate_dof_coordinates()[:source_space.dofmap.index_map.size_local]
        distance, nearest = cKDTree(source_points).query(points[missing]) if len(missing) else ([], [])
        # A node outside the source mesh must be a boundary node next to it, not another geometry.
        h = float(_dolfinx.cell_diameters(target_space.mesh).max(initial=0.0))
        if len(missing) and float(np.max(distance)) > h:
            raise ValueError(f"{len(missing)} target DOF coordinates lie outside the source mesh, up to "
                             f"{float(np.max(distance)):.3g} from it (more than a cell diameter {h:.3g}): "
                             "the meshes do not cover the same domain")
        self.missing, self.nearest = missing, np.asarray(nearest, dtype=np.int64)
        self.points = points
        self._function = dolfinx.fem.Function(source_space)

    def __call__(self, values) -> np.ndarray:
        values = np.atleast_2d(np.asarray(values, dtype=np.float64))
        if values.ndim != 2 or values.shape[1] != self.n_source:
            raise ValueError(f"values must have shape (B, {self.n_source}) (the source's owned velocity DOFs), "
                             f"got {values.shape}")
        out = np.empty((len(values), len(self.points), self.bs))
        for i, row in enumerate(values):
            self._function.x.array[:len(row)] = row   # owned DOFs; ghosts from their owners
            self._function.x.scatter_forward()
            out[i, self.found] = self._function.eval(self.points[self.found], self.cells)
            out[i, self.missing] = row.reshape(-1, self.bs)[self.nearest]
        return out.reshape(len(values), -1)


@functools.lru_cache(maxsize=2)
def _fine_reference(mesh_name: str, coarse_h, fine_h: float, pde: PdeConfig, count: int, steps: int,
                    spinup: int, perturbation: float, modes: int, seed: int) -> np.ndarray:
    """(steps + 1, count, n_coarse_u) fine-mesh converged states on the coarse velocity DOFs.

    Cached: the sweep of ``fempdl tradeoff`` trains one scene several times."""
    coarse = channel_problem(mesh.load(mesh_name, MPI.COMM_SELF, h=coarse_h), pde, controls=())
    fine = channel_problem(mesh.load(mesh_name, MPI.COMM_SELF, h=fine_h), pde)
    fine_u = torch.as_tensor(fine.fields["u"])
    solver = SolveLayer(fine, KSPOptions.preset("lu"))
    try:
        with torch.no_grad():
            u = torch.zeros(1, fine.control_size("w"), dtype=torch.float64)
            for _ in range(spinup):
                u = solver(w=u, u_prev=u)[:, fine_u]
            V = fine.field_space("u")
            coords = V.tabulate_dof_coordinates()[:V.dofmap.index_map.size_local]
            rng = np.random.default_rng(seed)
            noise = smooth_fields(coords, count, modes, rng, components=V.dofmap.index_map_bs)
            noise *= perturbation * pde.inflow / max(float(np.abs(noise).max()), 1e-300)
            u = u + torch.as_tensor(noise)
            states = [u]
            for _ in range(steps):
                u = solver(w=u, u_prev=u)[:, fine_u]
                states.append(u)
    finally:
        solver.close()
    transfer = VelocityTransfer(fine.field_space("u"), coarse.field_space("u"))
    return np.stack([transfer(state.numpy()) for state in states])


class HybridTask(Task):
    """Coarse Oseen stepper + network correction, trained over unrolled steps (module docstring)."""

    specs = (TaskSpec(name="hybrid", pdes=("oseen",), required=frozenset({"scene", "mesh", "pde", "hybrid"}),
                      optional=frozenset({"data", "network", "optimizer", "solver", "prdp"}),
                      unused={"data": frozenset({"truths", "noise", "resample", "train_rollout"})},
                      parallel=("data",)),)

    def __init__(self, scene: Scene, options: KSPOptions, *, comm: MPI.Comm = MPI.COMM_SELF,
                 seed: int | None = None):
        pde, hyb, data = scene.pde, scene.hybrid, scene.data
        self.steps, self.rollout = hyb.steps, data.rollout
        n_train, n_val = data.train, data.validation
        self.problem = channel_problem(mesh.load(scene.mesh.name, MPI.COMM_SELF, h=scene.mesh.h), pde)
        reference = _fine_reference(scene.mesh.name, scene.mesh.h, hyb.fine_h, pde,
                                    n_train + n_val, max(self.steps, self.rollout), hyb.spinup,
                                    hyb.perturbation, data.modes, data.seed)
        states = torch.as_tensor(reference, dtype=torch.float32)
        self.train_states, self.val_states = states[:, :n_train], states[:, n_train:]
        self.train_size, self.val_size = n_train, n_val
        self.u_dofs = torch.as_tensor(self.problem.fields["u"])
        free = ~np.isin(self.problem.fields["u"], self.problem.bc_dofs)
        torch.manual_seed(data.seed if seed is None else seed)
        self.model = ResidualMLP(len(self.u_dofs), scene.network.hidden, scene.network.layers,
                                 mask=torch.as_tensor(free, dtype=torch.float32), start_at_identity=True)
        self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                        scene.optimizer.lr, scene.optimizer.decay)
        self.layer = SolveLayer(self.problem, options, diff=scene.solver.diff)
        self.layers = [self.layer]
        self.warm_start = scene.solver.warm_start
        self.reference = SolveLayer(self.problem, KSPOptions.preset("lu"))
        with torch.no_grad():
            self.uncorrected_metric = float(self._rollout_errors(self.reference, lambda u: u, self.val_states,
                                                                 self.rollout).double().mean())

    def advance(self, layer: SolveLayer, u: torch.Tensor, steps: int, correct=None) -> list[torch.Tensor]:
        """``steps`` hybrid steps from velocities ``u`` (B, n_u); returns every new state."""
        correct = self.model if correct is None else correct
        out, solution = [], None
        for _ in range(steps):
            solution = layer(w=u, u_prev=u, **self._start(layer, u, solution))
            u = correct(solution[:, self.u_dofs])
            out.append(u)
        return out

    def _start(self, layer: SolveLayer, u: torch.Tensor, previous: torch.Tensor | None) -> dict:
        """With ``[solver] warm_start`` the capped solve starts from the state being
        advanced: velocity u, and the previous step's pressure (0 at the first step)."""
        if not (self.warm_start and layer is self.layer):
            return {}
        base = torch.zeros(u.shape[0], self.problem.output_size, dtype=u.dtype) if previous is None else previous
        return {"initial_guess": base.index_copy(1, self.u_dofs.long(), u.to(base.dtype))}

    def _rollout_errors(self, layer, correct, states, steps) -> torch.Tensor:
        """Per sample: the nMSE of every step of a ``steps``-step rollout, averaged over the steps."""
        predicted = self.advance(layer, states[0], steps, correct)
        return torch.stack([sample_nmse(u, ref) for u, ref in zip(predicted, states[1:])]).mean(0)

    def loss(self, idx) -> torch.Tensor:
        return self._rollout_errors(self.layer, self.model, self.train_states[:, idx], self.steps).mean()

    def validation_errors(self, idx) -> torch.Tensor:
        return self._rollout_errors(self.reference, self.model, self.val_states[:, idx], self.rollout)

    def k_eps_rhs(self) -> dict:
        """K_eps is measured on the first step of the validation samples."""
        u = self.val_states[0].double()
        return {"w": u, "u_prev": u, **self._start(self.layer, u, None)}

    def close(self) -> None:
        self.layer.close()
        self.reference.close()
