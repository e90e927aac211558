"""The inverse task (the PRDP paper's Poisson inverse problem): gradient descent on source amplitudes
through a capped solve. (Networks that learn to invert physics, the sip and hig tasks, are
:mod:`fempdl.app.tasks.learned_inverse`.)"""
from __future__ import annotations

from mpi4py import MPI
import numpy as np
import torch
from scipy.spatial import cKDTree

from fempdl import forms
from fempdl.app.schema import Scene, TaskSpec
from fempdl.app.tasks.base import Task, make_optimizer
from fempdl.app.tasks.data import source_modes
from fempdl.app.tasks.metrics import nmse
from fempdl.core import mesh
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.options import KSPOptions

__all__ = ["InverseTask"]


class _Theta(torch.nn.Module):
    def __init__(self, init):
        super().__init__()
        self.theta = torch.nn.Parameter(torch.tensor(init, dtype=torch.float64))


class InverseTask(Task):
    """Gradient descent on the source amplitudes theta through the capped Poisson layer.

    With ``[solver] warm_start`` each step's capped solve starts from the
    previous step's solution (a constant: the gradient is the layer's for the
    K-step map from it, as from zero). theta moves little per step, so K iterations from there go
    much further than K from zero, and the iterates converge over the steps.
    The solution is the task's state (:meth:`state_dict`): a resumed run
    continues from it.

    With ``comm`` of more than one rank the mesh is distributed over it: the
    layer, the modes and the reference hold each rank's owned DOFs, the nMSE
    sums over all ranks, and theta is replicated (its gradient is the sum of
    the ranks' contributions: the Trainer's ``parallel="mesh"``).
    """

    specs = (TaskSpec(name="inverse", pdes=("poisson",), required=frozenset({"scene", "mesh", "pde", "inverse"}),
                      optional=frozenset({"data", "optimizer", "solver", "prdp"}),
                      unused={"data": frozenset({"train", "validation", "modes", "rollout", "train_rollout", "truths",
                                                 "noise", "resample"}),
                              "optimizer": frozenset({"batch"})},
                      parallel=("mesh",), writes_fields=True),)

    train_size = 1

    def __init__(self, scene: Scene, options: KSPOptions, *, comm: MPI.Comm = MPI.COMM_SELF,
                 seed: int | None = None):
        msh = mesh.load(scene.mesh.name, comm, h=scene.mesh.h)
        pde = scene.pde
        self.comm = comm
        self.problem = forms.poisson.problem(msh, controls=("f",), kappa=pde.kappa, degree=pde.degree)
        self.theta_ref = torch.tensor(scene.inverse.theta_ref, dtype=torch.float64)
        self.modes = torch.as_tensor(source_modes(self.problem.dof_coordinates(), len(self.theta_ref), comm))
        reference = SolveLayer(self.problem, KSPOptions.preset("lu"))
        with torch.no_grad():
            self.u_ref = reference(f=self.modes @ self.theta_ref)
        reference.close()
        self.layer = SolveLayer(self.problem, options, diff=scene.solver.diff)
        self.layers = [self.layer]
        self.warm_start = bool(scene.solver.warm_start)
        self.last_solution = None                        # the last warm-started solve's output
        self.model = _Theta(scene.inverse.theta_init)
        self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                        scene.optimizer.lr, scene.optimizer.decay)

    def loss(self, idx) -> torch.Tensor:
        if self.warm_start and self.last_solution is not None:
            u = self.layer(f=self.modes @ self.model.theta, initial_guess=self.last_solution)
        else:
            u = self.layer(f=self.modes @ self.model.theta)
        if self.warm_start:
            self.last_solution = u.detach().clone()
        return nmse(u, self.u_ref, self.comm)

    def state_dict(self) -> dict:
        """The last solution on this rank's owned DOFs, with their coordinates (which place it on any partition)."""
        if self.last_solution is None:
            return {}
        return {"last_solution": self.last_solution,
                "coordinates": torch.as_tensor(self.problem.dof_coordinates())}

    def load_state_dict(self, states: list) -> None:
        """This rank's part of the saved solution, matched to its DOFs by coordinates."""
        for state in states:
            unknown = set(state) - {"last_solution", "coordinates"}
            if unknown:
                raise ValueError(f"InverseTask state holds 'last_solution' and 'coordinates', got {sorted(unknown)}")
        saved = [state for state in states if state]
        if not saved:
            self.last_solution = None                    # saved before the first step, or by an older fempdl
            return
        values = torch.cat([state["last_solution"].reshape(-1) for state in saved]).to(torch.float64)
        points = torch.cat([state["coordinates"] for state in saved]).to(torch.float64).numpy()
        ours = self.problem.dof_coordinates()
        if len(points) != len(values) or points.shape[1:] != ours.shape[1:]:
            raise ValueError(f"the saved solution has {len(values)} values at {len(points)} points; expected one "
                             f"value per point of dimension {ours.shape[1]}")
        distance, index = cKDTree(points).query(ours)
        size = float(np.ptp(points, axis=0).max()) if len(points) else 1.0
        owned = self.comm.allreduce(len(ours))
        if owned != len(points) or len(np.unique(index)) != len(index) or \
                (len(ours) and distance.max() > 1e-10 * size):
            raise ValueError(f"the saved solution does not lie on this mesh: {len(points)} saved points for "
                             f"{owned} DOFs, the farthest DOF {distance.max() if len(ours) else 0.0:.3g} from its "
                             "point (a different mesh or mesh size?)")
        leading = tuple(saved[0]["last_solution"].shape[:-1])              # the layer's batch shape, if any
        self.last_solution = values[torch.as_tensor(index)].reshape(*leading, -1)

    def validation_errors(self, idx) -> torch.Tensor:
        err = self.model.theta - self.theta_ref
        return ((err @ err) / (self.theta_ref @ self.theta_ref)).reshape(1)

    def k_eps_rhs(self) -> dict:
        return {"f": self.modes @ self.theta_ref}

    def validation_fields(self, idx) -> tuple:
        """("f", prediction, reference): the learned source against the true one, (1, n)."""
        with torch.no_grad():
            return "f", (self.modes @ self.model.theta)[None], (self.modes @ self.theta_ref)[None]

    def close(self) -> None:
        self.layer.close()
