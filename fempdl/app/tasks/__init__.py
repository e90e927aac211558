"""The scene tasks, one module each, and their one registry.

Every task class declares what it is in ``specs`` (:class:`~fempdl.app.schema.TaskSpec`: the scene
``task`` it serves, the PDEs, sections and keys it takes, its parallel modes and outputs). This
module collects them: the scene parser (:mod:`fempdl.app.scene`), the runner and the command read
:data:`SPECS`, and :func:`task_class` finds the class of a scene. Tasks that train through capped
layers are built as ``cls(scene, options, comm=..., seed=...)``, method tasks (SIP and HIG against
Adam) as ``cls(scene, method)``.
"""
from __future__ import annotations

import dataclasses

from fempdl.app.schema import TaskSpec
from fempdl.app.tasks.base import Task
from fempdl.app.tasks.emulator import EmulatorTask
from fempdl.app.tasks.hybrid import HybridTask
from fempdl.app.tasks.inverse import InverseTask
from fempdl.app.tasks.learned_inverse import InversionTask, method_of
from fempdl.app.tasks.marker import MarkerInversionTask
from fempdl.app.tasks.nonlinear_emulator import NonlinearEmulatorTask

__all__ = ["Task", "SPECS", "task_class", "spec_of", "method_of"]

_CLASSES = (EmulatorTask, NonlinearEmulatorTask, InverseTask, HybridTask, InversionTask, MarkerInversionTask)


def _registry() -> tuple[dict[str, TaskSpec], dict[tuple[str, str], type]]:
    """The specs by task name (the PDEs of every class serving it joined) and the class of each (task, PDE)."""
    specs: dict[str, TaskSpec] = {}
    classes: dict[tuple[str, str], type] = {}
    for cls in _CLASSES:
        for spec in cls.specs:
            for pde in spec.pdes:
                if (spec.name, pde) in classes:
                    raise ValueError(f"task {spec.name!r} on PDE {pde!r} is declared twice "
                                     f"({classes[spec.name, pde].__name__}, {cls.__name__})")
                classes[spec.name, pde] = cls
            known = specs.get(spec.name)
            if known is not None and dataclasses.replace(known, pdes=spec.pdes) != spec:
                raise ValueError(f"the classes serving task {spec.name!r} declare it differently")
            specs[spec.name] = spec if known is None else dataclasses.replace(known, pdes=known.pdes + spec.pdes)
    return specs, classes


#: Every task's declaration, by ``[scene] task``.
SPECS, _BY_TASK_AND_PDE = _registry()


def spec_of(task: str) -> TaskSpec:
    """The declaration of ``task``; ValueError naming the known tasks otherwise."""
    if task not in SPECS:
        raise ValueError(f"unknown task {task!r}; the tasks are {sorted(SPECS)}")
    return SPECS[task]


def task_class(task: str, pde: str) -> type:
    """The class that trains ``task`` on PDE type ``pde``; ValueError naming the known tasks, or the
    task's PDEs, otherwise."""
    cls = _BY_TASK_AND_PDE.get((task, pde))
    if cls is None:     # the spec only says why: an unknown task, or a PDE the task does not take
        raise ValueError(f"task {task!r} takes [pde] type {list(spec_of(task).pdes)}, got {pde!r}")
    return cls
