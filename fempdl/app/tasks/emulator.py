"""The emulator task (the PRDP paper's mixed chain): network step, then a capped physics step."""
from __future__ import annotations

from mpi4py import MPI
import numpy as np
import torch

from fempdl import forms
from fempdl.app.schema import NetworkConfig, Scene, TaskSpec
from fempdl.app.tasks.base import Task, make_optimizer, operator_pattern
from fempdl.app.tasks.data import smooth_fields
from fempdl.app.tasks.metrics import nmse, sample_nmse
from fempdl.app.tasks.networks import GraphConvNet, ResidualMLP, normalised_adjacency
from fempdl.core import mesh
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.options import KSPOptions

__all__ = ["EmulatorTask", "emulator_spec"]


def emulator_spec(pdes: tuple) -> TaskSpec:
    """The emulator task's declaration for the PDE types ``pdes`` (every class serving it declares it alike)."""
    return TaskSpec(name="emulator", pdes=pdes, required=frozenset({"scene", "mesh", "pde"}),
                    optional=frozenset({"data", "network", "optimizer", "solver", "prdp"}),
                    unused={"data": frozenset({"truths", "noise", "resample"})}, parallel=("data",),
                    writes_fields=True)


class EmulatorTask(Task):
    """Network step u0 -> u1, capped physics step u1 -> u2, loss nMSE(u2, u2_ref); with ``[data]
    train_rollout = M`` the chain of M (network, capped physics) pairs from u0, each pair's input
    the previous pair's output, and the loss the mean nMSE of the M states u2, u4, ..., u2M against
    the converged trajectory's (an autoregressive emulator trained over M pairs).

    The physics step is the scene's PDE: a heat step (control u0) or a
    linearised Burgers step around the network's output (w = u_prev = u1: the
    matrix itself depends on the network). Validation rolls out ``rollout``
    (network, converged physics) pairs from held-out states and averages the
    nMSE against the converged trajectory at every pair.
    """

    specs = (emulator_spec(("heat", "burgers")),)

    def __init__(self, scene: Scene, options: KSPOptions, *, comm: MPI.Comm = MPI.COMM_SELF,
                 seed: int | None = None):
        rng = np.random.default_rng(scene.data.seed)
        msh = mesh.load(scene.mesh.name, MPI.COMM_SELF, h=scene.mesh.h)
        pde = scene.pde
        self.pde = pde.type
        self.warm_start = scene.solver.warm_start
        self.problem = self._build_problem(msh, pde)
        n_train, n_val = scene.data.train, scene.data.validation
        self.rollout, self.train_rollout = scene.data.rollout, scene.data.train_rollout
        u0 = torch.as_tensor(self._initial_states(n_train + n_val, scene.data.modes, rng))
        # Converged physics: reference data and validation (not counted in layers' iterations).
        self.reference = self._reference_layer()
        with torch.no_grad():
            trajectory = [u0]
            for _ in range(2 * max(self.rollout, self.train_rollout)):
                trajectory.append(self.physics(self.reference, trajectory[-1]))
        self.reference_states = trajectory[1]
        self.train_u0 = u0[:n_train].float()
        # (M, n_train, n): the targets of the M pairs of the training chain
        self.train_targets = torch.stack([s[:n_train] for s in trajectory[2:2 * self.train_rollout + 1:2]]).float()
        self.val_u0 = u0[n_train:].float()
        self.val_targets = [state[n_train:].float() for state in trajectory[2:2 * self.rollout + 1:2]]
        self.train_size, self.val_size = n_train, n_val
        self.layer = self._capped_layer(options, scene)
        self.layers = [self.layer]
        torch.manual_seed(scene.data.seed if seed is None else seed)
        self.model = self._network(scene.network)
        self.optimizer, self.scheduler = make_optimizer(self.model.parameters(), scene.optimizer.type,
                                                        scene.optimizer.lr, scene.optimizer.decay)

    def _build_problem(self, msh, pde):
        if self.pde == "heat":
            return forms.heat.problem(msh, controls=("u0",), dt=pde.dt, theta=pde.theta, kappa=pde.kappa,
                                      degree=pde.degree)
        return forms.burgers.problem(msh, controls=("w", "u_prev"), nu=pde.nu, dt=pde.dt, degree=pde.degree)

    def _reference_layer(self):
        """The converged physics of the reference data and of validation."""
        return SolveLayer(self.problem, KSPOptions.preset("lu"))

    def _capped_layer(self, options, scene: Scene):
        """The layer the network trains through (its iterations are the run's cost)."""
        return SolveLayer(self.problem, options, diff=scene.solver.diff)

    def physics(self, layer: SolveLayer, u: torch.Tensor) -> torch.Tensor:
        """One step of the scene's PDE from state ``u`` through ``layer`` (the capped
        layer starts from ``u`` with ``[solver] warm_start``)."""
        inputs = self._step_inputs(u)
        if self.warm_start and layer is getattr(self, "layer", None):
            inputs["initial_guess"] = u
        return layer(**inputs)

    def _step_inputs(self, u: torch.Tensor) -> dict:
        return {"u0": u} if self.pde == "heat" else {"w": u, "u_prev": u}

    def _initial_states(self, count: int, modes: int, rng: np.random.Generator) -> np.ndarray:
        # Vector fields (Burgers) have blocked DOFs: one coordinate per node, gdim values each.
        return smooth_fields(self.problem.dof_coordinates(), count, modes, rng,
                             components=self.problem.V.dofmap.index_map_bs)

    def _network(self, spec: NetworkConfig) -> torch.nn.Module:
        n = self.problem.output_size
        if spec.type == "mlp":
            return ResidualMLP(n, spec.hidden, spec.layers)
        adjacency = normalised_adjacency(operator_pattern(self.problem)).to(torch.float32)
        return GraphConvNet(adjacency, self.problem.dof_coordinates()[:, :self.problem.V.mesh.geometry.dim],
                            spec.hidden, spec.layers)

    def loss(self, idx) -> torch.Tensor:
        u, errors = self.train_u0[idx], []
        for target in self.train_targets:
            u = self.physics(self.layer, self.model(u))
            errors.append(nmse(u, target[idx]))
        return torch.stack(errors).mean()

    def validation_errors(self, idx) -> torch.Tensor:
        """Per sample: the nMSE of every (network, converged step) pair, averaged over the rollout."""
        u, errors = self.val_u0[idx], []
        for target in self.val_targets:
            u = self.physics(self.reference, self.model(u))
            errors.append(sample_nmse(u, target[idx]))
        return torch.stack(errors).mean(0)

    def validation_fields(self, idx) -> tuple:
        """(space name, prediction, reference): the network's state after one
        (network, converged step) pair from the validation states ``idx``, and
        the converged trajectory's state there, (len(idx), n) in the solution space."""
        with torch.no_grad():
            u = self.physics(self.reference, self.model(self.val_u0[idx]))
        return None, u.double(), self.val_targets[0][idx].double()

    def close(self) -> None:
        self.layer.close()
        self.reference.close()

    def k_eps_rhs(self) -> dict:
        """Inputs on which K_eps is measured: the validation states (u1 -> u2 solves)."""
        states = self.reference_states[self.train_size:]
        inputs = self._step_inputs(states)
        if self.warm_start:
            inputs["initial_guess"] = states
        return inputs
