"""What a scene's ``[solver]`` section builds: the options of the task's capped layer.

A linear PDE's layer runs the scene's preset capped at K (:func:`solver_options`); a nonlinear
PDE's layer is plain Newton (full steps) around the preset (:func:`newton_options`), its two caps
then set by the runner through the task's :class:`~fempdl.methods.newton_caps.NewtonCaps`.
"""
from __future__ import annotations

from fempdl.app.schema import NONLINEAR_PDES, Scene
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.options import KSPOptions

__all__ = ["layer_options", "newton_options", "solver_options"]


def solver_options(scene: Scene, k: int | None, rtol: float | None = None) -> KSPOptions:
    """The scene's capped solver: ``k`` iterations, or run to ``rtol`` when ``k`` is None."""
    return KSPOptions.preset(scene.solver.preset, max_it=k, rtol=rtol,
                             lag_preconditioner=scene.solver.lag_preconditioner)


def newton_options(scene: Scene, rtol: float) -> NewtonOptions:
    """The training layer's Newton options from ``[solver]``: plain Newton (full steps, so a cap of N
    is exactly N Newton steps), its inner solve the preset: LU, or with ``refine = "newton"`` the
    Krylov preset run to ``rtol`` (converged), else capped (K moves it). The caps start at 1; the
    runner sets them through :class:`~fempdl.methods.newton_caps.NewtonCaps`."""
    solver = scene.solver
    if solver.preset == "lu":
        inner = KSPOptions.preset("lu")
    elif solver.refine == "newton":
        inner = KSPOptions.preset(solver.preset, max_it=None, rtol=rtol)
    else:
        inner = KSPOptions.preset(solver.preset, max_it=1)
    return NewtonOptions(max_it=1, snes_type="newton", ksp=inner)


def layer_options(scene: Scene, k: int | None) -> KSPOptions | NewtonOptions:
    """The options the task's capped layer is built with: the scene's capped solver at ``k``
    (:func:`solver_options`), or for a nonlinear PDE the Newton options of ``[solver]``
    (:func:`newton_options`, converged to the scene's ``k_eps_rtol`` where it is converged)."""
    if scene.pde.type in NONLINEAR_PDES:
        return newton_options(scene, scene.data.k_eps_rtol)
    return solver_options(scene, k)
