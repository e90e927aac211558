"""A scene resolved once: :class:`ScenePlan`, what the command, the runner and the reports train from.

A scene names its task and PDE; training it needs the task's declaration (:class:`TaskSpec`), its
class, the parallel mode it trains in and the caps of its runs, each checked against the scene.
:meth:`ScenePlan.of` looks the task up in the registry and runs those checks, once; the runner
(:func:`fempdl.app.runs.runner.train`) then builds and trains from the plan without looking up or
checking any of it again. A cap that no solve could take (beyond PETSc's int range, say) is refused
when the plan is made, before anything is written or trained.

The plan also carries what the scene's converged solves need once a run measured it (K_eps and, on
a Newton scene, the converged caps): later runs of the same scene take them instead of measuring.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Iterable

from mpi4py import MPI

from fempdl.app.schema import NONLINEAR_PDES, PARALLEL_MODES, Scene, TaskSpec
from fempdl.app.tasks import spec_of, task_class
from fempdl.app.tasks.solver_options import layer_options, solver_options
from fempdl.core import mesh
from fempdl.core.checks import check_int
from fempdl.methods.newton_caps import ConvergedCaps
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.options import MAX_PETSC_INT, KSPOptions

__all__ = ["ScenePlan", "RunCaps", "MODES", "check_caps", "batch_of"]

#: The run modes of a solver-cap scene: a fixed K, the converged cap K_eps, or PRDP moving K.
MODES = ("fixed", "converged", "prdp")


@dataclasses.dataclass(frozen=True)
class RunCaps:
    """The checked caps of one run (made by :meth:`ScenePlan.caps`).

    Attributes:
        mode: ``"fixed"``, ``"converged"`` or ``"prdp"`` (:data:`MODES`).
        k: the fixed cap K (fixed mode only, else None).
        options: what the task's capped layer is built with
            (:func:`~fempdl.app.tasks.solver_options.layer_options` at K, or 1 until the caps are set).
    """

    mode: str
    k: int | None
    options: KSPOptions | NewtonOptions


@dataclasses.dataclass(frozen=True)
class ScenePlan:
    """A scene with its task resolved and its runs' caps and parallel mode checked (:meth:`of`).

    Attributes:
        scene: the scene trained.
        spec: its task's declaration (the registry's, looked up once).
        task_class: the class that trains its task on its PDE.
        parallel: ``None`` (one process), ``"data"`` or ``"mesh"``, checked against ``spec``.
        planned: the caps checked when the plan was made (:meth:`caps` hands them out again).
        k_eps: the scene's K_eps once a run measured it (None: the next run measures it).
        converged: on a Newton scene, what converged solves need (the measurement behind ``k_eps``).
    """

    scene: Scene
    spec: TaskSpec
    task_class: type
    parallel: str | None = None
    planned: tuple[RunCaps, ...] = ()
    k_eps: int | None = None
    converged: ConvergedCaps | None = None

    @classmethod
    def of(cls, scene: Scene, *, parallel: str | None = None, caps: Iterable[tuple] = ()) -> ScenePlan:
        """Resolve ``scene``'s task (ValueError for an unknown one) and check the ``parallel`` mode and
        the ``caps`` of its runs, each ``(mode, k)`` or ``(mode, k, name)`` (:meth:`with_caps`)."""
        plan = cls(scene, spec_of(scene.task), task_class(scene.task, scene.pde.type))
        return (plan if parallel is None else plan.in_parallel(parallel)).with_caps(*caps)

    @classmethod
    def resolve(cls, scene: Scene | ScenePlan) -> ScenePlan:
        """``scene``'s plan: the plan itself, or a scene's made by :meth:`of` (serial, no caps checked yet)."""
        return scene if isinstance(scene, ScenePlan) else cls.of(scene)

    @property
    def name(self) -> str:
        return self.scene.name

    @property
    def batch(self) -> int:
        """The scene's mini-batch size (:func:`batch_of`)."""
        return batch_of(self.scene)

    def fingerprint(self, **settings) -> dict:
        """What defines a run of the scene, for the checkpoint's fingerprint: the parsed scene (not its
        file's location or description), the SHA-256 of its mesh file, and ``settings`` (mode, K, ...)."""
        scene = self.scene
        parsed = {key: value for key, value in scene.as_dict().items() if key not in ("source", "description")}
        # The mesh file's content, not only its name: a resume refuses a file that changed at the same path.
        return {"scene": parsed, "mesh_sha256": mesh.source_digest(scene.mesh.name, scene.mesh.h), **settings}

    @property
    def trains_methods(self) -> bool:
        """A sip or hig scene: it trains a method against Adam, not through solver caps."""
        return self.spec.trains == "method"

    def parallel_refusal(self, parallel: str | None) -> str | None:
        """Why the scene's task cannot train in the ``parallel`` mode (None if it can)."""
        if parallel not in (None, *PARALLEL_MODES):
            return f"parallel must be {_choices(None, *PARALLEL_MODES)}, got {parallel!r}"
        modes, scene = self.spec.parallel, self.scene
        if parallel is None or parallel in modes:
            return None
        if not modes:
            return (f"scene {scene.name!r}: {scene.task} scenes train on one process (the exact inverse assembles "
                    "serial scipy operators and HIG decomposes the whole batch's Jacobian at once); run them "
                    "without mpirun")
        if parallel == "data":
            return (f"scene {scene.name!r}: --parallel data splits batches of samples, and the {scene.task} "
                    f"task has one; use --parallel {modes[0]} instead")
        return (f"scene {scene.name!r}: --parallel mesh distributes the mesh, but the {scene.task} task's network "
                "(an MLP or graph network on whole DOF vectors) needs the whole field on every rank; use "
                f"--parallel {modes[0]} to spread its samples over the ranks instead")

    def in_parallel(self, parallel: str | None) -> ScenePlan:
        """This plan trained in the ``parallel`` mode; ValueError when its task cannot."""
        refusal = self.parallel_refusal(parallel)
        if refusal is not None:
            raise ValueError(refusal)
        return self if parallel == self.parallel else dataclasses.replace(self, parallel=parallel)

    def with_caps(self, *caps: tuple) -> ScenePlan:
        """This plan with the caps of more runs checked: each ``(mode, k)`` or ``(mode, k, name)``, ``name``
        the cap's name in a refusal (``"--k"`` for the command's flag; default ``"k"``)."""
        if not caps:
            return self
        checked = [self._check(*request) for request in caps]
        return dataclasses.replace(self, planned=self.planned + tuple(c for c in checked if c not in self.planned))

    def caps(self, mode: str, k: int | None = None) -> RunCaps:
        """The checked caps of a run in ``mode`` (``k``: fixed mode's K): the planned ones, or checked now
        (a trade-off's caps below K_eps are known only once K_eps is)."""
        return next((c for c in self.planned if (c.mode, c.k) == (mode, k)), None) or self._check(mode, k)

    def measured(self, k_eps: int | None, converged: ConvergedCaps | None = None) -> ScenePlan:
        """This plan with the scene's K_eps (and a Newton scene's converged caps) known: later runs take
        them instead of measuring again."""
        return dataclasses.replace(self, k_eps=k_eps, converged=converged)

    def require_caps(self) -> None:
        """Raise ValueError for a scene that compares training methods instead of solver caps."""
        if self.spec.trains != "cap":
            raise ValueError(f"scene {self.name!r} compares training methods, not solver caps: train it with "
                             "run_method (the commands `fempdl run` and `fempdl compare` do)")

    def build_task(self, options: KSPOptions | NewtonOptions, comm: MPI.Comm = MPI.COMM_WORLD,
                   seed: int | None = None):
        """The training task, its layer solving under ``options``: on a distributed mesh over ``comm``
        (``parallel="mesh"``), else the whole problem on each rank. ``seed`` initialises the network
        (default: the scene's data seed; the data stay the scene's)."""
        return self.task_class(self.scene, options, comm=comm if self.parallel == "mesh" else MPI.COMM_SELF,
                               seed=seed)

    def _check(self, mode: str, k: int | None = None, name: str = "k") -> RunCaps:
        if mode not in MODES:
            raise ValueError(f"mode must be one of {list(MODES)}, got {mode!r}")
        if (mode == "fixed") != (k is not None):
            raise ValueError("give k exactly when mode='fixed'")
        self.require_caps()
        check_caps(self.scene, mode, k, name)
        return RunCaps(mode, k, layer_options(self.scene, k or 1))


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


def batch_of(scene: Scene) -> int:
    """The scene's mini-batch size; the inverse task has none (its one sample is its batch)."""
    return 1 if scene.optimizer.batch is None else scene.optimizer.batch


def _choices(*values) -> str:
    """``None, 'data' or 'mesh'``: the values a refusal lists."""
    shown = [repr(v) for v in values]
    return ", ".join(shown[:-1]) + f" or {shown[-1]}"
