"""What PRDP's cap K means for a Newton layer: the Newton cap, the inner cap, or both.

A :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` has two caps: N Newton
steps (``max_it``) and K Krylov iterations per step (``inner_max_it``). PRDP
moves one number; :class:`NewtonCaps` is the PRDP target that says which cap it is:

* ``"newton"``: N = K, the inner solve as configured (a direct or converged inner
  solve: the PRDP paper's Newton-Raphson reading, where K = 1 is one Picard-like step);
* ``"inner"``: K Krylov iterations per step, the Newton cap as configured (capped too, as a rule:
  a converged Newton with K = 1 inner iteration per step seldom reaches its tolerance, and fails);
* ``"both"``: N = K and ``inner_per_k`` * K Krylov iterations per step: both
  refinements move together, the inner solve staying ``inner_per_k`` times finer
  than the Newton count. Once :func:`~fempdl.methods.k_eps.newton_k_eps` has measured what converged solves
  need (:class:`ConvergedCaps`, kept as ``converged``), neither cap exceeds its own
  converged value: N = min(K, N_eps) and min(``inner_per_k`` * K, inner_eps) iterations
  per step, so that K_eps, the larger of the two in units of K, does not run the other
  cap past convergence (K_eps Newton steps of K_eps iterations each where converged
  solves take N_eps steps).

Example:
    >>> ctrl = PRDP(NewtonCaps(layer, "both", inner_per_k=5), k0=1, dk=1, k_cap=8)
"""
from __future__ import annotations

import contextlib
import dataclasses
import math
from collections.abc import Iterator

from fempdl.core.checks import check_int
from fempdl.layer.cap_target import CapTarget
from fempdl.layer.newton_unrolled import check_unrolled_newton
from fempdl.solve.caps import Caps

__all__ = ["ConvergedCaps", "NewtonCaps", "REFINE"]

REFINE = ("newton", "inner", "both")


@dataclasses.dataclass(frozen=True)
class ConvergedCaps:
    """What converged solves need: the most Newton steps of a solve (N_eps) and the most inner
    iterations of a step (inner_eps), measured by :func:`~fempdl.methods.k_eps.converged_caps`."""

    newton_steps: int
    inner_iterations: int

    def __post_init__(self):
        check_int("ConvergedCaps.newton_steps", self.newton_steps, minimum=1)
        check_int("ConvergedCaps.inner_iterations", self.inner_iterations, minimum=1)


class NewtonCaps:
    """A PRDP target moving the caps of Newton layers by one rule (module docstring); a
    :class:`~fempdl.layer.cap_target.CapTarget` itself.

    Args:
        layers: a :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` or a list of them.
        refine: ``"newton"``, ``"inner"`` or ``"both"``.
        inner_per_k: with ``"both"``, the inner iterations per step per unit of K (>= 1).

    Attributes:
        converged: the :class:`ConvergedCaps` that bound the caps under ``"both"`` (set by
            :func:`~fempdl.methods.k_eps.newton_k_eps`, or assigned; None: unbounded).
    """

    def __init__(self, layers, refine: str = "newton", *, inner_per_k: int = 1):
        self.layers = list(layers) if isinstance(layers, (list, tuple)) else [layers]
        if not self.layers or not all(getattr(layer, "counts_newton_steps", False) for layer in self.layers):
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
            for layer in self.layers:       # what the layer would say when PRDP first sets K
                if layer.diff == "unrolled":
                    check_unrolled_newton(layer.options.with_inner_max_it(inner_per_k))
        self.refine, self.inner_per_k = refine, inner_per_k
        self.converged: ConvergedCaps | None = None
        self._k: int | None = None

    @property
    def problem(self):
        """The first layer's problem (PRDP reads its communicator)."""
        return self.layers[0].problem

    def as_target(self) -> CapTarget:
        return self

    @property
    def call(self):
        """What keyword inputs are passed to: the one layer (None for several)."""
        return self.layers[0] if len(self.layers) == 1 else None

    @property
    def counts_newton_steps(self) -> bool:
        """Whether K caps the Newton steps (``"newton"``, ``"both"``) or only the inner solve."""
        return self.refine in ("newton", "both")

    @property
    def k(self) -> int | None:
        """The K last set (None before PRDP sets it)."""
        return self._k

    @property
    def max_it(self) -> int | None:
        """The K last set (:attr:`k`); assigning sets K (:meth:`set_k`)."""
        return self._k

    @max_it.setter
    def max_it(self, k: int) -> None:
        self.set_k(k)

    def set_k(self, k: int) -> None:
        """Move every layer's caps to K under the rule."""
        check_int("K", k, minimum=1)
        newton, inner = k, (k if self.refine == "inner" else self.inner_per_k * k)
        if self.refine == "both" and self.converged is not None:
            newton, inner = min(newton, self.converged.newton_steps), min(inner, self.converged.inner_iterations)
        for layer in self.layers:
            caps = layer.caps
            layer.caps = Caps(newton if self.counts_newton_steps else caps.max_it,
                              inner if self.refine in ("inner", "both") else caps.inner_max_it)
        self._k = k

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        """Within the block the caps may move; K and every layer's caps are put back on exit."""
        k, saved = self._k, [layer.caps for layer in self.layers]
        try:
            yield
        finally:
            for layer, caps in zip(self.layers, saved):
                layer.caps = caps
            self._k = k

    def k_eps_from(self, counts: list) -> int:
        """K_eps from converged counts ``[(newton_steps, inner_iterations), ...]``, recorded as ``converged``."""
        self.converged = ConvergedCaps(max(1, max(n or 0 for n, _ in counts)), max(1, max(k for _, k in counts)))
        return self.k_eps

    @property
    def k_eps(self) -> int:
        """K_eps under the rule from ``converged``: N_eps (``"newton"``), inner_eps (``"inner"``), or the
        larger of N_eps and ceil(inner_eps / inner_per_k) (``"both"``)."""
        if self.converged is None:
            raise ValueError("K_eps needs the converged caps: measure them with newton_k_eps first")
        steps, per_step = self.converged.newton_steps, self.converged.inner_iterations
        if self.refine == "newton":
            return steps
        if self.refine == "inner":
            return per_step
        return max(steps, math.ceil(per_step / self.inner_per_k))

    def __repr__(self) -> str:
        extra = f", inner_per_k={self.inner_per_k}" if self.refine == "both" else ""
        return f"NewtonCaps({len(self.layers)} layer(s), refine={self.refine!r}{extra}, K={self._k})"
