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

A run trains from its scene's plan (:class:`~fempdl.app.runs.plan.ScenePlan`: the task resolved,
the parallel mode and the run's caps checked, K_eps once known): :func:`train` and
:func:`train_method` take a plan, as the command and the reports make it, once per command;
:func:`run` and :func:`run_method` make one from a scene and train it.
"""
from __future__ import annotations

import dataclasses
import logging
from pathlib import Path

from mpi4py import MPI
import torch

from fempdl.app.runs import files
from fempdl.app.runs.plan import MODES, RunCaps, ScenePlan, batch_of, check_caps
from fempdl.app.runs.result import RunResult
from fempdl.app.runs.settings import RunSettings
from fempdl.app.runs.training import Trainer
from fempdl.app.schema import Scene
from fempdl.app.tasks import SPECS
from fempdl.app.tasks.base import cap_target
from fempdl.app.tasks.solver_options import layer_options, solver_options
from fempdl.core import io
from fempdl.methods.k_eps import k_eps, newton_k_eps
from fempdl.methods.newton_caps import ConvergedCaps, NewtonCaps
from fempdl.methods.prdp import PRDP
from fempdl.solve.options import KSPOptions

# check_caps, MODES and the [solver] options (layer_options, solver_options) are re-exported: scripts
# and tests reach them as runner's, from before the plan held them.
__all__ = ["build_task", "check_caps", "check_parallel", "measure_k_eps", "run", "train",
           "run_method", "train_method", "save_fields", "RunResult", "MODES", "ScenePlan",
           "layer_options", "solver_options"]
_log = logging.getLogger(__name__)


def build_task(scene: Scene, options: KSPOptions, parallel: str | None = None,
               comm: MPI.Comm = MPI.COMM_WORLD, seed: int | None = None):
    """The training task of a solver-cap scene, with its layer solving under ``options``
    (:meth:`ScenePlan.build_task <fempdl.app.runs.plan.ScenePlan.build_task>` of the scene's plan in
    the ``parallel`` mode).

    ``parallel="mesh"`` distributes the mesh over ``comm``; every other mode
    builds the whole problem on each rank (``COMM_SELF``). ``seed`` initialises
    the network (default: the scene's data seed; the data stay the scene's)."""
    plan = ScenePlan.of(scene, parallel=parallel)
    plan.require_caps()
    return plan.build_task(options, comm, seed)


def check_parallel(scene: Scene, parallel: str | None) -> None:
    """Raise ``ValueError`` when the scene's task cannot train in the ``parallel`` mode
    (:meth:`~fempdl.app.runs.plan.ScenePlan.in_parallel`)."""
    ScenePlan.of(scene, parallel=parallel)


def field_tasks() -> list[str]:
    """The tasks whose validation predictions and references :func:`save_fields` writes."""
    return [name for name, spec in SPECS.items() if spec.writes_fields]


def measure_k_eps(task, scene: Scene, shard_over: MPI.Comm = MPI.COMM_SELF) -> int:
    """K_eps of ``task`` on its reference inputs (``task.k_eps_rhs()``) to the scene's ``k_eps_rtol``:
    :func:`~fempdl.methods.prdp.k_eps` of its first layer, or for a Newton task
    :func:`~fempdl.methods.newton_caps.newton_k_eps` under its caps' rule (which records the
    converged caps as ``task.caps.converged``). ``shard_over`` spreads the samples over its ranks."""
    rtol = scene.data.k_eps_rtol
    newton = task.caps                   # a Newton task's caps rule (None: K is the layers' max_it)
    if newton is not None:
        most = newton_k_eps(newton, rtol=rtol, shard_over=shard_over, **task.k_eps_rhs())
        _log.info("K_eps = %d (Newton, refine=%s, to rtol %s; what converged solves take at most: Newton steps "
                  "%d, inner iterations per step %d)", most, newton.refine, rtol,
                  newton.converged.newton_steps, newton.converged.inner_iterations)
        return most
    layer = task.layers[0]
    # A lagged preconditioner is set up once a call: probe it in calls of the training batch.
    batch = batch_of(scene) if layer.options.lag_preconditioner else 1
    most = k_eps(layer, rtol=rtol, shard_over=shard_over, batch=batch, **task.k_eps_rhs())
    _log.info("K_eps = %d (%s + %s to rtol %s)", most, layer.options.ksp_type, layer.options.pc_type, rtol)
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
    comm = task.problem.V.mesh.comm
    plot = task.problem.V.mesh.topology.dim == 2 and comm.size == 1
    if comm.rank == 0:      # recorded as fempdl's before they are written (fempdl.app.runs.files)
        files.record(out_dir, "fields.xdmf", "fields.h5", *(["fields.png"] if plot else []))
    fields = {"prediction": (name, prediction), "reference": (name, reference), "error": (name, prediction - reference)}
    paths = [io.write_fields(Path(out_dir) / "fields.xdmf", task.problem, fields, times=range(len(prediction)))]
    if plot:
        paths.append(io.plot_fields(Path(out_dir) / "fields.png", task.problem,
                                    {label: (n, v[0]) for label, (n, v) in fields.items()}, title=title,
                                    same_scale=("prediction", "reference")))
    return paths


def run(scene: Scene, mode: str, k: int | None = None, settings: RunSettings | None = None, *,
        k_eps_value: int | None = None, converged_caps: ConvergedCaps | None = None, **changes) -> RunResult:
    """Train ``scene`` in ``mode`` ("fixed" with ``k``, "converged" or "prdp") under ``settings``
    (:class:`~fempdl.app.runs.settings.RunSettings`; keyword ``changes`` replace its fields, e.g.
    ``run(scene, "prdp", out_dir=path)``): :func:`train` on the scene's plan, made and checked here.

    ``k_eps_value`` and, on a Newton scene, ``converged_caps`` (an earlier run's
    ``RunResult.converged_caps``) are taken instead of measured. With ``settings.save`` the
    validation fields are written after training (:func:`save_fields`; rank 0, or every rank of a
    distributed mesh)."""
    settings = dataclasses.replace(settings or RunSettings(), **changes)
    plan = ScenePlan.of(scene, parallel=settings.parallel, caps=[(mode, k)])
    return train(plan.measured(k_eps_value, converged_caps), plan.caps(mode, k), settings)


def train(plan: ScenePlan, caps: RunCaps, settings: RunSettings | None = None, **changes) -> RunResult:
    """Train the scene of ``plan`` with ``caps`` (one of its runs, :meth:`ScenePlan.caps
    <fempdl.app.runs.plan.ScenePlan.caps>`) under ``settings`` (keyword ``changes`` replace its fields).

    The plan was checked when it was made: nothing is looked up or checked again here but the
    settings. K_eps (and a Newton scene's converged caps) are the plan's when it knows them
    (:meth:`~fempdl.app.runs.plan.ScenePlan.measured`), else measured."""
    settings = dataclasses.replace(settings or RunSettings(), **changes) if changes else settings or RunSettings()
    settings.check_outputs()
    scene, out_dir, parallel, comm = plan.scene, settings.out_dir, plan.parallel, settings.comm
    if settings.parallel != parallel:      # the Trainer's ranks come from the settings, the task's from the plan
        raise ValueError(f"settings.parallel={settings.parallel!r} but the plan trains with parallel={parallel!r}: "
                         "make the plan in that mode (ScenePlan.in_parallel)")
    if settings.save and (out_dir is None or not plan.spec.writes_fields):
        raise ValueError(f"save=True writes validation fields of {field_tasks()} scenes into out_dir; got task "
                         f"{scene.task!r}, out_dir={out_dir!r}")
    task = plan.build_task(caps.options, comm, settings.seed)
    newton = task.caps                   # K_eps, the caps' rule and the converged caps follow from it
    try:
        keps, prdp = _set_caps(task, newton, plan, caps, comm if parallel == "data" else MPI.COMM_SELF)
        loop = dataclasses.replace(settings, epochs=settings.epochs or scene.optimizer.epochs,
                                   seed=scene.data.seed if settings.seed is None else settings.seed)
        trainer = Trainer(task, batch=plan.batch, settings=loop, prdp=prdp, stop_at=scene.optimizer.stop_at,
                          run_fingerprint=plan.fingerprint(mode=caps.mode, k=caps.k, seed=settings.seed))
        rows = trainer.run()
        if settings.save and (parallel == "mesh" or comm.rank == 0):    # a distributed mesh: every rank writes
            save_fields(task, out_dir, title=f"{scene.name}, {caps.mode}" + (f" K={caps.k}" if caps.k else ""))
    finally:
        task.close()
    return RunResult(scene=scene.name, mode=caps.mode, k_eps=keps, rows=rows,
                     out_dir=None if out_dir is None else str(out_dir),
                     converged_caps=None if newton is None else newton.converged)


def _set_caps(task, newton: NewtonCaps | None, plan: ScenePlan, caps: RunCaps,
              shard_over: MPI.Comm) -> tuple[int, PRDP | None]:
    """K_eps (the plan's, else measured) and the caps of the run: K (fixed), K_eps (converged) or the
    PRDP controller that moves them, all through the task's :func:`cap_target`. A Newton task's
    (``newton``, its caps rule ``task.caps``) converged caps are the plan's, else measured (with K_eps)
    unless its rule needs none of them."""
    scene, known = plan.scene, plan.k_eps
    if newton is not None:
        if plan.converged is not None:
            newton.converged = plan.converged
        elif known is None or newton.refine != "newton":
            measure_k_eps(task, scene, shard_over)
        keps = newton.k_eps if known is None else known
    else:
        keps = measure_k_eps(task, scene, shard_over) if known is None else known
    if newton is not None and newton.refine == "inner":     # K caps the inner solve; Newton takes the converged steps
        for layer in task.layers:
            layer.max_it = newton.converged.newton_steps
    target = cap_target(task)
    if caps.mode == "prdp":
        return keps, PRDP(target, dataclasses.replace(scene.prdp, k_cap=scene.prdp.k_cap or keps))
    target.set_k(caps.k if caps.mode == "fixed" else keps)
    return keps, None


def run_method(scene: Scene, method: str, settings: RunSettings | None = None, **changes) -> RunResult:
    """Train a sip or hig scene with ``method`` (its own, or "backprop") under ``settings`` (keyword
    ``changes`` replace its fields); metrics and checkpoints in ``settings.out_dir``. A resumed run
    can be extended to equal training time with ``stop_at_time``. Method runs train on one process
    from the scene's seed and write no fields. :func:`train_method` on the scene's plan."""
    return train_method(ScenePlan.of(scene), method, settings, **changes)


def train_method(plan: ScenePlan, method: str, settings: RunSettings | None = None, **changes) -> RunResult:
    """:func:`run_method` on a scene already planned (:class:`~fempdl.app.runs.plan.ScenePlan`)."""
    settings = dataclasses.replace(settings or RunSettings(), **changes) if changes else settings or RunSettings()
    settings.check_outputs()
    refused = [name for name in ("seed", "parallel", "save") if getattr(settings, name) not in (None, False)]
    if refused:
        raise ValueError(f"run_method trains on one process from the scene's seed and writes no fields; "
                         f"got {', '.join(f'{n}={getattr(settings, n)!r}' for n in refused)}")
    scene = plan.scene
    task = plan.task_class(scene, method)
    try:
        loop = dataclasses.replace(settings, epochs=settings.epochs or scene.optimizer.epochs, seed=scene.data.seed)
        trainer = Trainer(task, batch=scene.optimizer.batch, settings=loop, stop_at=scene.optimizer.stop_at,
                          run_fingerprint=plan.fingerprint(method=method))
        rows = trainer.run()
    finally:
        task.close()
    return RunResult(scene=scene.name, mode=method, k_eps=None, rows=rows,
                     out_dir=None if settings.out_dir is None else str(settings.out_dir))
