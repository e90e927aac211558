"""The inverse task (the PRDP paper's Poisson inverse problem): gradient descent on source amplitudes."""
from __future__ import annotations

import torch
from mpi4py import MPI

from fempdl import forms, mesh
from fempdl.app.scene import Scene
from fempdl.app.tasks.base import Task, make_optimizer
from fempdl.app.tasks.data import source_modes
from fempdl.app.training import nmse
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

__all__ = ["InverseTask"]


class _Theta(torch.nn.Module):
    def __init__(self, init):
        super().__init__()
        self.theta = torch.nn.Parameter(torch.tensor(init, dtype=torch.float64))


class InverseTask(Task):
    """Gradient descent on the source amplitudes theta through the capped Poisson layer.

    With ``comm`` of more than one rank the mesh is distributed over it: the
    layer, the modes and the reference hold each rank's owned DOFs, the nMSE
    sums over all ranks, and theta is replicated (its gradient is the sum of
    the ranks' contributions: the Trainer's ``parallel="mesh"``).
    """

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
        self.model = _Theta(scene.inverse.theta_init)
        self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                        scene.optimizer.lr, scene.optimizer.decay)

    def loss(self, idx) -> torch.Tensor:
        u = self.layer(f=self.modes @ self.model.theta)
        return nmse(u, self.u_ref, self.comm)

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
