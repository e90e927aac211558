"""Runs of a scene: a solver-cap mode (fixed K, converged K_eps or PRDP) or a training method (SIP, HIG, Adam).

A run mode is ``("fixed", K)``, ``("converged", None)`` (fixed K = K_eps) or
``("prdp", None)`` (K from the scene's [prdp] block, refined on plateaus).
K_eps, the "converged" cap, is the most iterations the scene's solver
(``[solver] preset``) needs to reach the scene's ``k_eps_rtol`` on the task's
reference inputs. sip and hig scenes run with :func:`run_method`.

On a nonlinear PDE the task's layer is a Newton solve and K means what
``[solver] refine`` says (:class:`~fempdl.methods.newton_caps.NewtonCaps`, the
task's ``caps``): Newton steps, inner iterations per step, or both. K_eps is
then :func:`~fempdl.methods.newton_caps.newton_k_eps` under that rule, and
fixed K, K_eps and PRDP all set K through the same ``caps``. The measurement
behind K_eps (:class:`~fempdl.methods.newton_caps.ConvergedCaps`: the most Newton
steps and inner iterations of a step converged solves need on the reference inputs)
bounds the caps under ``refine = "both"``, and with ``refine = "inner"`` the Newton
cap is its Newton steps. A run returns it (``RunResult.converged_caps``) so that
later runs of the same scene take it (``converged_caps=``) instead of measuring again.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

import torch
from mpi4py import MPI

from fempdl.core import io, mesh
from fempdl.app.schema import NONLINEAR_PDES, SEED_MAX, Scene
from fempdl.app.tasks import SPECS, spec_of, task_class
from fempdl.app.tasks.nonlinear_emulator import newton_options
from fempdl.app.runs.training import CHECKPOINT_EVERY, Trainer
from fempdl.app.tasks.base import cap_target, set_cap
from fempdl.layer.solve_layer import SolveLayer
from fempdl.solve.options import MAX_PETSC_INT, KSPOptions
from fempdl.core.checks import check_int
from fempdl.core.parallel import shard
from fempdl.methods.newton_caps import ConvergedCaps, NewtonCaps
from fempdl.methods.newton_caps import converged_caps as measure_converged_caps     # run() takes converged_caps=
from fempdl.methods.prdp import PRDP

__all__ = ["build_task", "check_caps", "check_parallel", "k_eps", "layer_options", "newton_caps_eps", "run",
           "run_method", "run_settings", "save_fields", "RunResult", "MODES"]
_log = logging.getLogger(__name__)

MODES = ("fixed", "converged", "prdp")


@dataclasses.dataclass
class RunResult:
    """What a run produced; ``rows`` are the per-epoch metrics of :class:`Trainer`.

    ``mode`` is a run mode of :data:`MODES`, or the training method of a sip or
    hig scene (:mod:`fempdl.app.tasks.inversion`), whose runs have no ``k_eps``.
    ``converged_caps``: on a Newton scene, what converged solves need (the measurement
    behind ``k_eps``; pass it to :func:`run` with ``k_eps_value``), else None."""

    scene: str
    mode: str
    k_eps: int | None
    rows: list
    out_dir: str | None
    converged_caps: ConvergedCaps | None = None

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
    def newton_steps(self) -> int | None:
        """Newton steps, forward and unrolled backward (None for a run without Newton layers)."""
        return self.rows[-1].get("newton_steps")

    @property
    def k_schedule(self) -> list[tuple[int, int]]:
        """(first epoch, K) for every K used."""
        out = []
        for row in self.rows:
            if not out or out[-1][1] != row["k"]:
                out.append((row["epoch"], row["k"]))
        return out


def build_task(scene: Scene, options: KSPOptions, parallel: str | None = None,
               comm: MPI.Comm = MPI.COMM_WORLD, seed: int | None = None):
    """The training task of a solver-cap scene, with its layer solving under ``options``.

    ``parallel="mesh"`` distributes the mesh over ``comm``; every other mode
    builds the whole problem on each rank (``COMM_SELF``). ``seed`` initialises
    the network (default: the scene's data seed; the data stay the scene's)."""
    check_parallel(scene, parallel)
    if spec_of(scene.task).trains != "cap":
        raise ValueError(f"scene {scene.name!r} compares training methods, not solver caps: train it with "
                         "run_method (the commands `fempdl run` and `fempdl compare` do)")
    cls = task_class(scene.task, scene.pde.type)
    return cls(scene, options, comm=comm if parallel == "mesh" else MPI.COMM_SELF, seed=seed)


def check_parallel(scene: Scene, parallel: str | None) -> None:
    """Raise ``ValueError`` when the scene's task cannot train in the ``parallel`` mode."""
    if parallel not in (None, "data", "mesh"):
        raise ValueError(f"parallel must be None, 'data' or 'mesh', got {parallel!r}")
    modes = spec_of(scene.task).parallel
    if parallel is None or parallel in modes:
        return
    if not modes:
        raise ValueError(f"scene {scene.name!r}: {scene.task} scenes train on one process (the exact inverse "
                         "assembles serial scipy operators and HIG decomposes the whole batch's Jacobian at once); "
                         "run them without mpirun")
    if parallel == "data":
        raise ValueError(f"scene {scene.name!r}: --parallel data splits batches of samples, and the {scene.task} "
                         f"task has one; use --parallel {modes[0]} instead")
    raise ValueError(f"scene {scene.name!r}: --parallel mesh distributes the mesh, but the {scene.task} task's "
                     "network (an MLP or graph network on whole DOF vectors) needs the whole field on every "
                     f"rank; use --parallel {modes[0]} to spread its samples over the ranks instead")


def field_tasks() -> list[str]:
    """The tasks whose validation predictions and references :func:`save_fields` writes."""
    return [name for name, spec in SPECS.items() if spec.writes_fields]


def check_caps(scene: Scene, mode: str, k: int | None = None, name: str = "k") -> None:
    """Raise ValueError when a run of ``scene`` in ``mode`` could not take its caps: ``k`` (named
    ``name``) in fixed mode, ``[prdp] k0`` and ``k_cap`` in PRDP mode. Checked before anything is
    built or trained: a cap beyond PETSc's int range used to be refused only when it was first set,
    after K_eps was measured (and, in the command, after the baseline had trained)."""
    caps = [(f"{name} {k!r}" if name.startswith("--") else f"{name}={k!r}", k)] if mode == "fixed" else []
    if mode == "prdp" and scene.prdp is not None:
        caps += [(f"[prdp] {key} = {value!r}", value) for key, value in
                 (("k0", scene.prdp.k0), ("k_cap", scene.prdp.k_cap)) if value is not None]
    for shown, cap in caps:
        try:
            if scene.pde.type in NONLINEAR_PDES:     # K counts Newton steps or inner iterations, each a PETSc int
                check_int("K", cap, minimum=1, maximum=MAX_PETSC_INT)
            else:
                solver_options(scene, cap)
        except (TypeError, ValueError) as err:
            raise ValueError(f"{shown} cannot cap the solver of scene {scene.name!r}: {err}") from None


def solver_options(scene: Scene, k: int | None, rtol: float | None = None) -> KSPOptions:
    """The scene's capped solver: ``k`` iterations, or run to ``rtol`` when ``k`` is None."""
    return KSPOptions.preset(scene.solver.preset, max_it=k, rtol=rtol,
                             lag_preconditioner=scene.solver.lag_preconditioner)


def layer_options(scene: Scene, k: int | None):
    """The options the task's capped layer is built with: the scene's capped solver at ``k``
    (:func:`solver_options`), or for a nonlinear PDE the Newton options of ``[solver]``, whose caps
    the runner sets through the task's ``caps``."""
    if scene.pde.type in NONLINEAR_PDES:
        return newton_options(scene, scene.data.k_eps_rtol)
    return solver_options(scene, k)


def newton_caps_eps(task, rtol: float, shard_over: MPI.Comm = MPI.COMM_SELF) -> int:
    """K_eps of a Newton task under its caps' rule, as :func:`~fempdl.methods.newton_caps.newton_k_eps`
    measures it: the converged caps of the task's reference inputs (spread over ``shard_over``'s ranks,
    the maximum theirs), recorded as ``task.caps.converged``."""
    inputs = {name: torch.atleast_2d(value) for name, value in task.k_eps_rhs().items()}
    idx = shard(torch.arange(next(iter(inputs.values())).shape[0]), shard_over)
    local = (measure_converged_caps(task.caps.layers[0], rtol=rtol, **{name: value[idx] for name, value in inputs.items()})
             if len(idx) else ConvergedCaps(1, 1))
    task.caps.converged = ConvergedCaps(*(shard_over.allreduce(count, op=MPI.MAX)
                                          for count in (local.newton_steps, local.inner_iterations)))
    most = task.caps.k_eps
    _log.info("K_eps = %d (Newton, refine=%s, to rtol %s; what converged solves take at most: Newton steps %d, "
              "inner iterations per step %d)", most, task.caps.refine, rtol, task.caps.converged.newton_steps,
              task.caps.converged.inner_iterations)
    return most


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
    (one XDMF time step per sample), and on a 2D mesh on one process
    ``fields.png`` (prediction, reference and error of the first sample). On a
    distributed mesh every rank calls it (the XDMF file is written together)."""
    idx = torch.arange(min(samples, task.val_size))
    name, prediction, reference = task.validation_fields(idx)
    fields = {"prediction": (name, prediction), "reference": (name, reference), "error": (name, prediction - reference)}
    paths = [io.write_fields(Path(out_dir) / "fields.xdmf", task.problem, fields, times=range(len(prediction)))]
    if task.problem.V.mesh.topology.dim == 2 and task.problem.V.mesh.comm.size == 1:
        paths.append(io.plot_fields(Path(out_dir) / "fields.png", task.problem,
                                    {label: (n, v[0]) for label, (n, v) in fields.items()}, title=title,
                                    same_scale=("prediction", "reference")))
    return paths


def run_settings(scene: Scene, **settings) -> dict:
    """What defines a run of ``scene``, for the checkpoint's fingerprint: the parsed
    scene (not its file's location or description), the SHA-256 of its mesh file,
    and ``settings`` (mode, K, ...)."""
    parsed = {key: value for key, value in scene.as_dict().items() if key not in ("source", "description")}
    # The mesh file's content, not only its name: a resume refuses a file that changed at the same path.
    return {"scene": parsed, "mesh_sha256": mesh.source_digest(scene.mesh.name, scene.mesh.h), **settings}


def run(scene: Scene, mode: str, k: int | None = None, *, out_dir: Path | None = None, resume: bool = False,
        epochs: int | None = None, progress: bool = False, k_eps_value: int | None = None,
        converged_caps: ConvergedCaps | None = None, stop_after: int | None = None, parallel: str | None = None,
        comm: MPI.Comm = MPI.COMM_WORLD, seed: int | None = None, save: bool = False,
        tensorboard: bool = False, overwrite: bool = False,
        checkpoint_every: float = CHECKPOINT_EVERY) -> RunResult:
    """Train ``scene`` in ``mode`` ("fixed" with ``k``, "converged" or "prdp").

    ``parallel`` ("data" or "mesh") trains on the ranks of ``comm`` together
    (:mod:`fempdl.core.parallel`); every rank returns the same result. ``seed``
    sets the network initialisation and the minibatch order (default: the
    scene's data seed); the data are the scene's either way. ``save`` writes
    the validation fields after training (:func:`save_fields`, into
    ``out_dir``; rank 0, or every rank of a distributed mesh). ``tensorboard`` also
    writes the metrics as TensorBoard scalars into ``out_dir``/tensorboard. An
    ``out_dir`` holding an earlier run needs ``resume`` (continue it) or
    ``overwrite`` (replace it). ``checkpoint_every``: the seconds between writes of the files
    (:class:`~fempdl.app.runs.training.Trainer`). ``k_eps_value`` and, on a Newton scene,
    ``converged_caps`` (an earlier run's ``RunResult.converged_caps``) are taken instead of measured."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
    if save and (out_dir is None or not spec_of(scene.task).writes_fields):
        raise ValueError(f"save=True writes validation fields of {field_tasks()} scenes into out_dir; got task "
                         f"{scene.task!r}, out_dir={out_dir!r}")
    if (mode == "fixed") != (k is not None):
        raise ValueError("give k exactly when mode='fixed'")
    check_caps(scene, mode, k)
    if seed is not None and (isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed <= SEED_MAX):
        raise ValueError(f"seed must be an int in [0, 2^63 - 1] (what torch's and numpy's generators take), "
                         f"got {seed!r}")
    task = build_task(scene, layer_options(scene, k or 1), parallel, comm, seed)
    try:
        keps, prdp = _set_caps(task, scene, mode, k, k_eps_value, converged_caps,
                               comm if parallel == "data" else MPI.COMM_SELF)
        trainer = Trainer(task, epochs=epochs or scene.optimizer.epochs, batch=_batch(scene),
                          out_dir=out_dir, prdp=prdp, seed=scene.data.seed if seed is None else seed,
                          progress=progress, tensorboard=_board_dir(out_dir, tensorboard),
                          stop_after=stop_after, stop_at=scene.optimizer.stop_at, parallel=parallel, comm=comm,
                          settings=run_settings(scene, mode=mode, k=k, seed=seed), overwrite=overwrite,
                          checkpoint_every=checkpoint_every)
        rows = trainer.run(resume=resume)
        if save and (parallel == "mesh" or comm.rank == 0):    # a distributed mesh is written by all ranks
            save_fields(task, out_dir, title=f"{scene.name}, {mode}" + (f" K={k}" if k else ""))
    finally:
        task.close()
    caps = getattr(task, "caps", None)
    return RunResult(scene=scene.name, mode=mode, k_eps=keps, rows=rows,
                     out_dir=None if out_dir is None else str(out_dir),
                     converged_caps=caps.converged if isinstance(caps, NewtonCaps) else None)


def _set_caps(task, scene: Scene, mode: str, k: int | None, k_eps_value: int | None,
              converged: ConvergedCaps | None, shard_over: MPI.Comm) -> tuple[int, PRDP | None]:
    """K_eps (measured unless given) and the caps of ``mode``: K (fixed), K_eps (converged) or the
    PRDP controller that moves them, all through the task's :func:`cap_target`. A Newton task's
    converged caps are measured (with K_eps) unless given, or unless its rule needs none of them."""
    newton = isinstance(getattr(task, "caps", None), NewtonCaps)
    if newton:
        if converged is not None:
            task.caps.converged = converged
        elif k_eps_value is None or task.caps.refine != "newton":
            newton_caps_eps(task, scene.data.k_eps_rtol, shard_over)
        keps = task.caps.k_eps if k_eps_value is None else k_eps_value
    elif k_eps_value is not None:
        keps = k_eps_value
    else:
        keps = k_eps(task, solver_options(scene, None, scene.data.k_eps_rtol), shard_over=shard_over,
                     batch=_batch(scene))
    if newton and task.caps.refine == "inner":     # K caps the inner solve; Newton takes the converged steps
        for layer in task.layers:
            layer.max_it = task.caps.converged.newton_steps
    target = cap_target(task)
    if mode == "prdp":
        return keps, PRDP(target, dataclasses.replace(scene.prdp, k_cap=scene.prdp.k_cap or keps))
    set_cap(target, k if mode == "fixed" else keps)
    return keps, None


def _board_dir(out_dir: Path | None, tensorboard: bool) -> Path | None:
    if tensorboard and out_dir is None:
        raise ValueError("tensorboard=True writes into out_dir/tensorboard: give out_dir")
    return Path(out_dir) / "tensorboard" if tensorboard else None


def _batch(scene: Scene) -> int:
    """The scene's mini-batch size; the inverse task has none (its one sample is its batch)."""
    return 1 if scene.optimizer.batch is None else scene.optimizer.batch


def run_method(scene: Scene, method: str, *, out_dir: Path | None = None, resume: bool = False, epochs: int | None = None,
        progress: bool = False, stop_after: int | None = None, stop_at_time: float | None = None,
        tensorboard: bool = False, overwrite: bool = False, checkpoint_every: float = CHECKPOINT_EVERY) -> RunResult:
    """Train a sip or hig scene with ``method`` (its own, or "backprop"); metrics and checkpoints in ``out_dir``.

    ``stop_at_time`` ends the run once its training steps took that many
    seconds (a resumed run can so be extended to equal training time)."""
    task = task_class(scene.task, scene.pde.type)(scene, method)
    try:
        trainer = Trainer(task, epochs=epochs or scene.optimizer.epochs, batch=scene.optimizer.batch,
                          out_dir=out_dir, seed=scene.data.seed, progress=progress, stop_after=stop_after,
                          tensorboard=_board_dir(out_dir, tensorboard),
                          stop_at=scene.optimizer.stop_at, stop_at_time=stop_at_time,
                          settings=run_settings(scene, method=method), overwrite=overwrite,
                          checkpoint_every=checkpoint_every)
        rows = trainer.run(resume=resume)
    finally:
        task.close()
    return RunResult(scene=scene.name, mode=method, k_eps=None, rows=rows,
                     out_dir=None if out_dir is None else str(out_dir))
