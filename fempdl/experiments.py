"""Scene -> training task, and the runs that compare capped, PRDP and converged physics.

Three tasks, chosen by the scene's ``task`` (sip and hig scenes, which compare
training methods, are trained by :mod:`fempdl.inversion`):

* ``emulator`` (the PRDP paper's mixed chain): a network maps u0 to u1, the
  capped physics layer maps u1 to u2, and the training loss is the nMSE of u2
  against two converged steps. The physics is a heat step, or a Burgers step
  linearised around the network's output (w = u_prev = u1: the network's output
  enters the matrix). The validation metric rolls out ``[data] rollout``
  (network, physics) pairs on held-out states with *converged* physics (LU) in
  place of the capped layer, so every K is judged alike: a network that learned
  to lean on an unconverged solver shows it here.
* ``inverse`` (the paper's Poisson inverse problem): the source is a sum of P
  smooth modes f = Phi theta; gradient descent on theta minimises the nMSE of
  the capped Poisson solution against the solution for theta_ref. The
  validation metric is ||theta - theta_ref||^2 / ||theta_ref||^2.
* ``hybrid`` (:mod:`fempdl.hybrid`): a coarse Oseen stepper plus a network
  correction, trained over unrolled steps against a fine-mesh reference.

Training data are float32 (as in the paper); references are computed with LU.
K_eps, the "converged" cap, is the largest number of iterations the scene's
solver (``[solver] preset``) needs to reach the scene's ``k_eps_rtol``
(default 1e-5) on the reference data.

A run mode is ``("fixed", K)``, ``("converged", None)`` (fixed K = K_eps) or
``("prdp", None)`` (K from the scene's [prdp] block, refined on plateaus).
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import numpy as np
import torch
from mpi4py import MPI

from fempdl import forms, io, mesh
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions
from fempdl.networks import GraphConvNet, ResidualMLP, normalised_adjacency
from fempdl.parallel import shard
from fempdl.prdp import PRDP
from fempdl.scene import Scene
from fempdl.system import assemble_scipy
from fempdl.training import Trainer, nmse, sample_nmse

__all__ = ["build_task", "k_eps", "run", "run_settings", "save_fields", "RunResult", "MODES", "FIELD_TASKS"]
_log = logging.getLogger(__name__)

MODES = ("fixed", "converged", "prdp")
#: Tasks whose validation predictions and references :func:`save_fields` writes.
FIELD_TASKS = ("emulator", "inverse")


@dataclasses.dataclass
class RunResult:
    """What a run produced; ``rows`` are the per-epoch metrics of :class:`Trainer`.

    ``mode`` is a run mode of :data:`MODES`, or the training method of a sip or
    hig scene (:mod:`fempdl.inversion`), whose runs have no ``k_eps``."""

    scene: str
    mode: str
    k_eps: int | None
    rows: list
    out_dir: str | None

    @property
    def final_metric(self) -> float:
        return self.rows[-1]["val_metric"]

    @property
    def total_iterations(self) -> int:
        return self.rows[-1]["total_iterations"]

    @property
    def wall_time(self) -> float:
        return self.rows[-1]["wall_time"]

    @property
    def k_schedule(self) -> list[tuple[int, int]]:
        """(first epoch, K) for every K used."""
        out = []
        for row in self.rows:
            if not out or out[-1][1] != row["k"]:
                out.append((row["epoch"], row["k"]))
        return out


def smooth_fields(coords: np.ndarray, count: int, modes: int, rng: np.random.Generator,
                  components: int = 1) -> np.ndarray:
    """(count, n * components) random sums of sine modes over the bounding box, amplitudes ~ 1/|mode|^2.

    ``coords`` (n, 3) are node coordinates; with ``components`` > 1 every
    component is an independent field and the values are blocked per node
    (x0, y0, x1, y1, ...), the DOF order of a vector space."""
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    dims = [d for d in range(coords.shape[1]) if hi[d] > lo[d]]
    unit = (coords[:, dims] - lo[dims]) / (hi[dims] - lo[dims])
    out = np.zeros((count, len(coords), components))
    for index in np.ndindex(*([modes] * len(dims))):
        wave = np.array(index) + 1
        shape = np.prod(np.sin(np.pi * wave[None, :] * unit), axis=1)
        out += (rng.standard_normal((count, 1, components)) / float(wave @ wave)) * shape[None, :, None]
    return out.reshape(count, -1)


def source_modes(coords: np.ndarray, count: int, comm: MPI.Comm = MPI.COMM_SELF) -> np.ndarray:
    """(n, P) smooth modes phi_p(x) = prod_d sin(p pi x_d) over the bounding box.

    ``coords`` are this rank's rows; the box is that of all ranks of ``comm``."""
    lo, hi = coords.min(axis=0), coords.max(axis=0)
    comm.Allreduce(MPI.IN_PLACE, lo, op=MPI.MIN)
    comm.Allreduce(MPI.IN_PLACE, hi, op=MPI.MAX)
    dims = [d for d in range(coords.shape[1]) if hi[d] > lo[d]]
    unit = (coords[:, dims] - lo[dims]) / (hi[dims] - lo[dims])
    return np.stack([np.prod(np.sin(np.pi * p * unit), axis=1) for p in range(1, count + 1)], axis=1)


def optimisation_step(optimizer, loss: torch.Tensor) -> float:
    """One step of ``optimizer`` on ``loss``; returns the loss value."""
    optimizer.zero_grad()
    loss.backward()
    optimizer.step()
    return loss.item()


class Task:
    """What :class:`~fempdl.training.Trainer` trains; subclasses define the physics.

    A task has ``model``, ``optimizer``, ``scheduler`` (or None), ``layers``
    (the capped layers whose iterations are counted), ``train_size``,
    ``val_size``, and two functions of sample indices (a LongTensor):

    * ``loss(idx)``: the training loss of those samples, a mean over them (so a
      batch split into shards is the shard losses weighted by their sizes);
    * ``validation_errors(idx)``: one error per validation sample; the
      validation metric is their mean over all ``val_size`` samples.

    ``train_step(idx)`` is one step of ``optimizer`` on ``loss(idx)``; a task
    whose optimizer makes its own update (HIG, :mod:`fempdl.inversion`)
    replaces it. A task may also define ``start_epoch(epoch)``, which the
    Trainer calls before every epoch (to draw new training data).
    """

    val_size = 1

    def train_step(self, idx) -> float:
        """One optimizer step on the samples ``idx``; returns the loss."""
        return optimisation_step(self.optimizer, self.loss(idx))

    def validate(self) -> float:
        """The validation metric: the mean error over every validation sample."""
        with torch.no_grad():
            return float(self.validation_errors(torch.arange(self.val_size)).double().mean())


class EmulatorTask(Task):
    """Network step u0 -> u1, capped physics step u1 -> u2, loss nMSE(u2, u2_ref).

    The physics step is the scene's PDE: a heat step (control u0) or a
    linearised Burgers step around the network's output (w = u_prev = u1: the
    matrix itself depends on the network). Validation rolls out ``rollout``
    (network, converged physics) pairs from held-out states and averages the
    nMSE against the converged trajectory at every pair.
    """

    def __init__(self, scene: Scene, options: KSPOptions, seed: int | None = None):
        rng = np.random.default_rng(scene.data["seed"])
        msh = mesh.load(scene.mesh["name"], MPI.COMM_SELF, h=scene.mesh["h"])
        pde = scene.pde
        self.pde = pde["type"]
        self.warm_start = scene.solver["warm_start"]
        if self.pde == "heat":
            self.problem = forms.heat.problem(msh, controls=("u0",), dt=pde["dt"], theta=pde["theta"],
                                              kappa=pde["kappa"], degree=pde["degree"])
        else:
            self.problem = forms.burgers.problem(msh, controls=("w", "u_prev"), nu=pde["nu"], dt=pde["dt"],
                                                 degree=pde["degree"])
        n_train, n_val = scene.data["train"], scene.data["validation"]
        self.rollout = scene.data["rollout"]
        u0 = torch.as_tensor(self._initial_states(n_train + n_val, scene.data["modes"], rng))
        # Converged physics: reference data and validation (not counted in layers' iterations).
        self.reference = SolveLayer(self.problem, KSPOptions.preset("lu"))
        with torch.no_grad():
            trajectory = [u0]
            for _ in range(2 * self.rollout):
                trajectory.append(self.physics(self.reference, trajectory[-1]))
        self.reference_states = trajectory[1]
        self.train_u0, self.train_u2 = u0[:n_train].float(), trajectory[2][:n_train].float()
        self.val_u0 = u0[n_train:].float()
        self.val_targets = [state[n_train:].float() for state in trajectory[2::2]]
        self.train_size, self.val_size = n_train, n_val
        self.layer = SolveLayer(self.problem, options, diff=scene.solver["diff"])
        self.layers = [self.layer]
        torch.manual_seed(scene.data["seed"] if seed is None else seed)
        self.model = self._network(scene.network)
        self.optimizer, self.scheduler = make_optimizer(scene.optimizer, self.model.parameters())

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

    def _network(self, spec: dict) -> torch.nn.Module:
        n = self.problem.output_size
        if spec["type"] == "mlp":
            return ResidualMLP(n, spec["hidden"], spec["layers"])
        adjacency = normalised_adjacency(operator_pattern(self.problem)).to(torch.float32)
        return GraphConvNet(adjacency, self.problem.dof_coordinates()[:, :self.problem.V.mesh.geometry.dim],
                            spec["hidden"], spec["layers"])

    def loss(self, idx) -> torch.Tensor:
        u2 = self.physics(self.layer, self.model(self.train_u0[idx]))
        return nmse(u2, self.train_u2[idx])

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

    def __init__(self, scene: Scene, options: KSPOptions, comm: MPI.Comm = MPI.COMM_SELF):
        msh = mesh.load(scene.mesh["name"], comm, h=scene.mesh["h"])
        pde = scene.pde
        self.comm = comm
        self.problem = forms.poisson.problem(msh, controls=("f",), kappa=pde["kappa"], degree=pde["degree"])
        self.theta_ref = torch.tensor(scene.inverse["theta_ref"], dtype=torch.float64)
        self.modes = torch.as_tensor(source_modes(self.problem.dof_coordinates(), len(self.theta_ref), comm))
        reference = SolveLayer(self.problem, KSPOptions.preset("lu"))
        with torch.no_grad():
            self.u_ref = reference(f=self.modes @ self.theta_ref)
        reference.close()
        self.layer = SolveLayer(self.problem, options, diff=scene.solver["diff"])
        self.layers = [self.layer]
        self.model = _Theta(scene.inverse["theta_init"])
        self.optimizer, self.scheduler = make_optimizer(scene.optimizer, self.model.parameters())

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


def operator_pattern(problem) -> "sp.csr_matrix":
    """The assembled operator without boundary conditions: its pattern is the DOF graph."""
    return assemble_scipy(problem.a_form)


def make_optimizer(spec: dict, params):
    params = list(params)
    if spec["type"] == "adam":
        # The fused kernel updates all parameters in one call: the per-tensor loop of
        # the default implementation costs more than these small networks' arithmetic.
        optimizer = torch.optim.Adam(params, lr=spec["lr"], fused=True)
    else:
        optimizer = torch.optim.SGD(params, lr=spec["lr"])
    scheduler = None if spec["decay"] == 1.0 else torch.optim.lr_scheduler.ExponentialLR(optimizer, spec["decay"])
    return optimizer, scheduler


def build_task(scene: Scene, options: KSPOptions, parallel: str | None = None,
               comm: MPI.Comm = MPI.COMM_WORLD, seed: int | None = None):
    """The training task of a scene, with its layer solving under ``options``.

    ``parallel="mesh"`` distributes the mesh over ``comm``; every other mode
    builds the whole problem on each rank (``COMM_SELF``). ``seed`` initialises
    the network (default: the scene's data seed; the data stay the scene's)."""
    check_parallel(scene, parallel)
    if scene.task in ("sip", "hig"):
        raise ValueError(f"scene {scene.name!r} compares training methods, not solver caps: train it with "
                         "fempdl.inversion.run (the commands `fempdl run` and `fempdl compare` do)")
    if scene.task == "hybrid":
        from fempdl.hybrid import HybridTask
        return HybridTask(scene, options, seed)
    if scene.task == "emulator":
        return EmulatorTask(scene, options, seed)
    return InverseTask(scene, options, comm if parallel == "mesh" else MPI.COMM_SELF)


def check_parallel(scene: Scene, parallel: str | None) -> None:
    """Raise ``ValueError`` when the scene's task cannot train in the ``parallel`` mode."""
    if parallel not in (None, "data", "mesh"):
        raise ValueError(f"parallel must be None, 'data' or 'mesh', got {parallel!r}")
    if parallel is not None and scene.task in ("sip", "hig"):
        raise ValueError(f"scene {scene.name!r}: {scene.task} scenes train on one process (the exact inverse "
                         "assembles serial scipy operators and HIG decomposes the whole batch's Jacobian at once); "
                         "run them without mpirun")
    if parallel == "data" and scene.task == "inverse":
        raise ValueError(f"scene {scene.name!r}: --parallel data splits batches of samples, and the inverse task "
                         "has one; use --parallel mesh to distribute its mesh instead")
    if parallel == "mesh" and scene.task != "inverse":
        raise ValueError(f"scene {scene.name!r}: --parallel mesh distributes the mesh, but the {scene.task} task's "
                         "network (an MLP or graph network on whole DOF vectors) needs the whole field on every "
                         "rank; use --parallel data to spread its samples over the ranks instead")


def solver_options(scene: Scene, k: int | None, rtol: float | None = None) -> KSPOptions:
    """The scene's capped solver: ``k`` iterations, or run to ``rtol`` when ``k`` is None."""
    return KSPOptions.preset(scene.solver["preset"], max_it=k, rtol=rtol,
                             lag_preconditioner=scene.solver["lag_preconditioner"])


def k_eps(task, options: KSPOptions, shard_over: MPI.Comm = MPI.COMM_SELF, batch: int = 1) -> int:
    """Largest iteration count the solver needs to reach its rtol on the task's reference inputs.

    With ``shard_over`` the samples are spread over its ranks (data-parallel
    runs, where every rank holds the whole problem) and the maximum is theirs.
    A lagged preconditioner is probed in calls of ``batch`` samples, as it trains."""
    probe = SolveLayer(task.problem, dataclasses.replace(options, engine="petsc"))
    inputs = {name: torch.atleast_2d(value) for name, value in task.k_eps_rhs().items()}
    size = batch if options.lag_preconditioner else 1
    with torch.no_grad():
        idx = shard(torch.arange(next(iter(inputs.values())).shape[0]), shard_over)
        for chunk in idx.split(size):
            probe(**{name: value[chunk] for name, value in inputs.items()})
    most = shard_over.allreduce(probe.stats.max_forward_iterations, op=MPI.MAX)
    probe.close()
    _log.info("K_eps = %d (%s + %s to rtol %s)", most, options.ksp_type, options.pc_type, options.rtol)
    return most


def save_fields(task, out_dir: Path, samples: int = 4, title: str | None = None) -> list[Path]:
    """Write the task's validation predictions against their references
    (``task.validation_fields``) into ``out_dir``: ``fields.xdmf`` with the
    prediction, reference and error of the first ``samples`` validation samples
    (one XDMF time step per sample), and on a 2D mesh ``fields.png``
    (prediction, reference and error of the first sample). One process."""
    idx = torch.arange(min(samples, task.val_size))
    name, prediction, reference = task.validation_fields(idx)
    fields = {"prediction": (name, prediction), "reference": (name, reference), "error": (name, prediction - reference)}
    paths = [io.write_fields(Path(out_dir) / "fields.xdmf", task.problem, fields, times=range(len(prediction)))]
    if task.problem.V.mesh.topology.dim == 2:
        paths.append(io.plot_fields(Path(out_dir) / "fields.png", task.problem,
                                    {label: (n, v[0]) for label, (n, v) in fields.items()}, title=title,
                                    same_scale=("prediction", "reference")))
    return paths


def run_settings(scene: Scene, **settings) -> dict:
    """What defines a run of ``scene``, for the checkpoint's fingerprint: the parsed
    scene (not its file's location or description) and ``settings`` (mode, K, ...)."""
    parsed = {key: value for key, value in scene.as_dict().items() if key not in ("source", "description")}
    return {"scene": parsed, **settings}


def run(scene: Scene, mode: str, k: int | None = None, *, out_dir: Path | None = None, resume: bool = False,
        epochs: int | None = None, progress: bool = False, k_eps_value: int | None = None,
        stop_after: int | None = None, parallel: str | None = None,
        comm: MPI.Comm = MPI.COMM_WORLD, seed: int | None = None, save: bool = False) -> RunResult:
    """Train ``scene`` in ``mode`` ("fixed" with ``k``, "converged" or "prdp").

    ``parallel`` ("data" or "mesh") trains on the ranks of ``comm`` together
    (:mod:`fempdl.parallel`); every rank returns the same result. ``seed``
    sets the network initialisation and the minibatch order (default: the
    scene's data seed); the data are the scene's either way. ``save`` writes
    the validation fields after training (:func:`save_fields`, into
    ``out_dir``; rank 0; not with ``parallel="mesh"``)."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
    if save and (out_dir is None or scene.task not in FIELD_TASKS or parallel == "mesh"):
        raise ValueError(f"save=True writes validation fields of {list(FIELD_TASKS)} scenes into out_dir, serial "
                         f"or with parallel='data'; got task {scene.task!r}, out_dir={out_dir!r}, "
                         f"parallel={parallel!r}")
    if (mode == "fixed") != (k is not None):
        raise ValueError("give k exactly when mode='fixed'")
    task = build_task(scene, solver_options(scene, k or 1), parallel, comm, seed)
    keps = k_eps_value if k_eps_value is not None else k_eps(
        task, solver_options(scene, None, scene.data["k_eps_rtol"]),
        shard_over=comm if parallel == "data" else MPI.COMM_SELF, batch=scene.optimizer.get("batch", 1))
    prdp = None
    if mode == "converged":
        task.layer.max_it = keps
    elif mode == "prdp":
        p = scene.prdp
        prdp = PRDP(task.layers, k0=p["k0"], dk=p["dk"], tau_step=p["tau_step"], tau_stop=p["tau_stop"],
                    delta=p["delta"], ema_window=p["ema_window"], k_cap=p["k_cap"] or keps,
                    guard=p["guard"], growth=p["growth"])
    trainer = Trainer(task, epochs=epochs or scene.optimizer["epochs"], batch=scene.optimizer.get("batch", 1),
                      out_dir=out_dir, prdp=prdp, seed=scene.data["seed"] if seed is None else seed,
                      progress=progress,
                      stop_after=stop_after, stop_at=scene.optimizer["stop_at"], parallel=parallel, comm=comm,
                      settings=run_settings(scene, mode=mode, k=k, seed=seed))
    try:
        rows = trainer.run(resume=resume)
        if save and comm.rank == 0:
            save_fields(task, out_dir, title=f"{scene.name}, {mode}" + (f" K={k}" if k else ""))
    finally:
        task.close()
    return RunResult(scene=scene.name, mode=mode, k_eps=keps, rows=rows,
                     out_dir=None if out_dir is None else str(out_dir))
