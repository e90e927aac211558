"""The scene tasks, one module each, found by the scene's ``task`` (and, for method scenes, its PDE).

Solver-cap tasks (trained with a fixed K, K_eps or PRDP) are built as
``TASKS[scene.task](scene, options, comm=..., seed=...)``; method tasks (SIP
and HIG against Adam) as ``METHOD_TASKS[scene.pde.type](scene, method)``.
"""
from fempdl.app.tasks.base import Task
from fempdl.app.tasks.emulator import EmulatorTask
from fempdl.app.tasks.hybrid import HybridTask
from fempdl.app.tasks.inverse import InverseTask
from fempdl.app.tasks.inversion import InversionTask, method_of
from fempdl.app.tasks.marker import MarkerInversionTask

__all__ = ["Task", "TASKS", "METHOD_TASKS", "method_of"]

#: Tasks that train through capped layers, by ``[scene] task``.
TASKS = {"emulator": EmulatorTask, "inverse": InverseTask, "hybrid": HybridTask}
#: Tasks of the sip and hig scenes, by ``[pde] type``: the marker's physics is a rollout, the others one layer.
METHOD_TASKS = {"poisson": InversionTask, "heat": InversionTask, "marker": MarkerInversionTask}
