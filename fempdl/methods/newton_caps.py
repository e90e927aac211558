"""What PRDP's cap K means for a Newton layer: the Newton cap, the inner cap, or both.

A :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` has two caps: N Newton
steps (``max_it``) and K Krylov iterations per step (``inner_max_it``). PRDP
moves one number; :class:`NewtonCaps` is the PRDP target that says which cap it is:

* ``"newton"``: N = K, the inner solve as configured (a direct or converged inner
  solve: the PRDP paper's Newton-Raphson reading, where K = 1 is one Picard-like step);
* ``"inner"``: K Krylov iterations per step, the Newton cap as configured;
* ``"both"``: N = K and ``inner_per_k`` * K Krylov iterations per step: both
  refinements move together, the inner solve staying ``inner_per_k`` times finer
  than the Newton count.

Example:
    >>> ctrl = PRDP(NewtonCaps(layer, "both", inner_per_k=5), k0=1, dk=1, k_cap=8)
"""
from __future__ import annotations

import dataclasses
import math

import torch

from fempdl.core.checks import check_int
from fempdl.layer.newton_layer import NonlinearSolveLayer

__all__ = ["NewtonCaps", "REFINE", "newton_k_eps"]

REFINE = ("newton", "inner", "both")


class NewtonCaps:
    """A PRDP target moving the caps of Newton layers by one rule (module docstring).

    Args:
        layers: a :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` or a list of them.
        refine: ``"newton"``, ``"inner"`` or ``"both"``.
        inner_per_k: with ``"both"``, the inner iterations per step per unit of K (>= 1).
    """

    def __init__(self, layers, refine: str = "newton", *, inner_per_k: int = 1):
        self.layers = list(layers) if isinstance(layers, (list, tuple)) else [layers]
        if not self.layers or not all(hasattr(layer, "inner_max_it") for layer in self.layers):
            raise TypeError("NewtonCaps moves the caps of NonlinearSolveLayers; pass one or a list of them")
        if refine not in REFINE:
            raise ValueError(f"refine must be one of {list(REFINE)}, got {refine!r}")
        check_int("inner_per_k", inner_per_k, minimum=1)
        if refine != "both" and inner_per_k != 1:
            raise ValueError("inner_per_k applies to refine='both'")
        if refine in ("inner", "both"):
            direct = [i for i, layer in enumerate(self.layers) if layer.options.ksp.direct]
            if direct:
                raise ValueError(f"refine={refine!r} caps the inner Krylov solve, but layer(s) {direct} solve each "
                                 "step directly; give them an iterative inner solve (e.g. ksp='cg')")
        self.refine, self.inner_per_k = refine, inner_per_k
        self._k: int | None = None

    @property
    def problem(self):
        """The first layer's problem (PRDP reads its communicator)."""
        return self.layers[0].problem

    @property
    def max_it(self) -> int | None:
        """The K last set (None before PRDP sets it)."""
        return self._k

    @max_it.setter
    def max_it(self, k: int) -> None:
        check_int("K", k, minimum=1)
        for layer in self.layers:
            if self.refine in ("newton", "both"):
                layer.max_it = k
            if self.refine == "inner":
                layer.inner_max_it = k
            elif self.refine == "both":
                layer.inner_max_it = self.inner_per_k * k
        self._k = k

    def caps(self) -> tuple:
        """(Newton cap, inner cap) of the first layer."""
        return self.layers[0].max_it, self.layers[0].inner_max_it

    def __repr__(self) -> str:
        extra = f", inner_per_k={self.inner_per_k}" if self.refine == "both" else ""
        return f"NewtonCaps({len(self.layers)} layer(s), refine={self.refine!r}{extra}, K={self._k})"


def newton_k_eps(caps: NewtonCaps, *, rtol: float = 1e-8, **controls) -> int:
    """K_eps of a Newton layer under ``caps``' rule: the least K at which converged solves of
    ``controls`` (the layer's keyword inputs, e.g. validation samples) need no more than the caps
    allow, measured by a probe layer (Newton to ``rtol``, the inner solve to ``rtol``): the most
    Newton steps (``"newton"``), the most inner iterations of a step (``"inner"``), or the larger of
    the steps and ceil(inner iterations / inner_per_k) (``"both"``). Use it as PRDP's ``k_cap``."""
    if not controls:
        raise ValueError("give the inputs to measure K_eps on as keyword arguments")
    layer = caps.layers[0]
    ksp = layer.options.ksp
    inner = ksp if ksp.direct else dataclasses.replace(ksp, max_it=None, rtol=rtol, atol=None, divtol=None,
                                                        adjoint=None, engine="petsc", options_prefix=None)
    options = dataclasses.replace(layer.options, max_it=None, rtol=rtol, ksp=inner)
    probe = NonlinearSolveLayer(layer.problem, options)
    try:
        with torch.no_grad():
            probe(**controls)
        steps, per_step = probe.stats.max_newton_steps, probe.stats.max_forward_iterations
    finally:
        probe.close()
    if caps.refine == "newton":
        return max(steps, 1)
    if caps.refine == "inner":
        return max(per_step, 1)
    return max(steps, math.ceil(per_step / caps.inner_per_k), 1)
