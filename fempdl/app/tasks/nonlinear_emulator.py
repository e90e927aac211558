"""The emulator task on a nonlinear step: the mixed chain through a (capped) Newton solve.

The PDE "nonlinear-heat" is one backward-Euler step of nonlinear heat conduction,
(u - u0) / dt - div(kappa (1 + alpha u^2) grad u) = 0, u = 0 on the boundary
(:mod:`fempdl.forms.nonlinear_diffusion`), solved by plain Newton (full steps) in a
:class:`~fempdl.layer.newton_layer.NonlinearSolveLayer`. Its two caps (Newton steps N,
inner Krylov iterations per step) are moved by one number K through
:class:`~fempdl.methods.newton_caps.NewtonCaps` by the scene's ``[solver] refine``
rule: ``caps`` is what the runner sets K on (fixed K, K_eps, PRDP). With
``[solver] warm_start`` Newton starts from the state being advanced, so K = 1 with
``refine = "newton"`` is one linearised step from it (the PRDP paper's Picard-like
simplification: its matrix is Newton's Jacobian at that state). The reference data
and validation use converged plain Newton (full steps, LU, rtol 1e-10) from the state.
"""
from __future__ import annotations

import torch

from fempdl import forms
from fempdl.app.schema import Scene
from fempdl.app.tasks.emulator import EmulatorTask, emulator_spec
from fempdl.layer.newton_layer import NonlinearSolveLayer
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.solve.newton_options import NewtonOptions

__all__ = ["NonlinearEmulatorTask", "REFERENCE_RTOL"]

#: Relative residual of the converged reference Newton solves (data and validation).
REFERENCE_RTOL = 1e-10


class NonlinearEmulatorTask(EmulatorTask):
    """Network step u0 -> u1, capped Newton step u1 -> u2, loss nMSE(u2, u2_ref) (module docstring).

    Attributes:
        caps: the :class:`NewtonCaps` of the training layer under ``[solver] refine``.
    """

    specs = (emulator_spec(("nonlinear-heat",)),)

    def __init__(self, scene: Scene, options: NewtonOptions, **kwargs):
        super().__init__(scene, options, **kwargs)
        solver = scene.solver
        self.caps = NewtonCaps(self.layers, solver.refine,
                               inner_per_k=solver.inner_per_k if solver.refine == "both" else 1)

    def _build_problem(self, msh, pde):
        return forms.nonlinear_diffusion.problem(msh, ("u0",), dt=pde.dt, kappa=pde.kappa, alpha=pde.alpha,
                                                 degree=pde.degree, f=0.0)

    def _reference_layer(self):
        return NonlinearSolveLayer(self.problem, NewtonOptions(ksp="lu", rtol=REFERENCE_RTOL))

    def _capped_layer(self, options, scene: Scene):
        return NonlinearSolveLayer(self.problem, options, diff=scene.solver.diff)

    def physics(self, layer, u: torch.Tensor) -> torch.Tensor:
        """One Newton step solve from state ``u``: the reference always starts from ``u`` (it converges
        either way, in fewer steps), the capped layer with ``[solver] warm_start``."""
        inputs = self._step_inputs(u)
        if layer is self.reference or self.warm_start:
            inputs["initial_guess"] = u
        return layer(**inputs)

    def _step_inputs(self, u: torch.Tensor) -> dict:
        return {"u0": u}
