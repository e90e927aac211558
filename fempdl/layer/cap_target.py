"""What PRDP moves: one protocol, :class:`CapTarget`, and :func:`as_target`, which makes one of anything
a user may hand PRDP, :func:`~fempdl.methods.k_eps.k_eps`, :func:`~fempdl.methods.k_start.k_start` or
:func:`~fempdl.methods.preflight.preflight`.

A user passes a solve layer, a list of them, a :class:`~fempdl.methods.newton_caps.NewtonCaps` rule,
a :class:`~fempdl.layer.rollout.Rollout`, another object whose cap is its ``max_it`` attribute (a SIP
inverse's Gauss-Newton iterations), a function ``f(k)`` or ``None``. Each of those objects that knows
its caps says how K moves them through its own ``as_target()``; :func:`as_target` asks it, and wraps
the rest. The methods then see one interface:

* ``layers``: the solve layers whose :class:`~fempdl.solve.caps.Caps` K moves (their counters, health
  checks and communicators are what PRDP and K_eps read);
* ``set_k(k)``: move the caps to K; ``k``: the K in force (None where unknown);
* ``kept()``: a block after which the caps (and the target's K) are as before;
* ``k_eps_from(counts)``: K_eps from converged solves' counts;
* ``call``: what keyword inputs are passed to (a layer or a rollout), ``None`` when ambiguous;
* ``counts_newton_steps``: whether K caps Newton steps (else Krylov iterations);
* ``converged``: the measured :class:`~fempdl.methods.newton_caps.ConvergedCaps` of a Newton rule, else
  ``None``.
"""
from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Protocol

import torch

from fempdl.core.checks import check_int

__all__ = ["CapTarget", "LayerCaps", "CapFunction", "MaxItAttribute", "CapTargets", "as_target", "layers_target",
           "solve_layers_in", "k_eps_of_counts"]


class CapTarget(Protocol):
    """The interface of everything PRDP moves (module docstring)."""

    layers: tuple
    call: Callable | None
    counts_newton_steps: bool
    converged: object | None

    @property
    def k(self) -> int | None: ...

    def set_k(self, k: int) -> None: ...

    def kept(self) -> contextlib.AbstractContextManager: ...

    def k_eps_from(self, counts: list) -> int: ...


def as_target(target) -> CapTarget:
    """``target`` as a :class:`CapTarget`: its own ``as_target()`` (layers, rollouts, NewtonCaps), its
    ``max_it`` attribute, the solve layers inside a torch module, a list's targets together, a function
    ``f(k)`` or ``None`` (nothing moves)."""
    if hasattr(target, "as_target"):
        return target.as_target()
    if target is None:
        return CapTargets(())
    if hasattr(target, "max_it"):
        return MaxItAttribute(target)
    if isinstance(target, torch.nn.Module):          # a model holding its layers (callable and iterable too)
        return CapTargets(tuple(as_target(t) for t in solve_layers_in(target)))
    if isinstance(target, Mapping):
        raise TypeError(f"a PRDP target is not a mapping; pass its values: PRDP(list(targets.values()), ...) "
                        f"(got a {type(target).__name__} with keys {list(target)[:5]})")
    if isinstance(target, Iterable) and not isinstance(target, (str, bytes)):
        return CapTargets(tuple(as_target(t) for t in target))
    if callable(target):
        return CapFunction(target)
    raise TypeError(f"a PRDP target is a SolveLayer, a NonlinearSolveLayer, a NewtonCaps, a Rollout, an object with a "
                    f"max_it attribute, a list of them, a callable f(k) or None; got a {type(target).__name__}, which "
                    "has no max_it attribute")


def solve_layers_in(module) -> list:
    """The outermost modules inside ``module`` that know their caps (solve layers, rollouts: a rollout's
    step layer is its own), in registration order; a TypeError naming what to pass where there is none."""
    found, inside = [], set()
    for name, sub in module.named_modules():
        if any(name.startswith(prefix) for prefix in inside):
            continue
        if hasattr(sub, "as_target"):
            found.append(sub)
            inside.add(f"{name}." if name else "")
    if not found:
        raise TypeError(f"the {type(module).__name__} passed as a target holds no solve layer or rollout; pass "
                        "the layer(s) whose cap K moves, e.g. PRDP(model.layer, ...)")
    return found


def layers_target(target, what: str = "target") -> CapTarget:
    """``target`` as a :class:`CapTarget` that moves solve layers (what K_eps, k0 and preflight measure);
    a TypeError naming ``what`` and, in a list, the item that is none."""
    try:
        found = as_target(target)
    except TypeError:
        found = None
    if found is None or not found.layers:
        got = type(target).__name__
        if isinstance(target, (list, tuple)):
            bad = [i for i, part in enumerate(target) if not _is_solve_target(part)]
            got += f" whose item {bad[0]} is a {type(target[bad[0]]).__name__}" if bad else ""
        raise TypeError(f"{what} must be a SolveLayer, a NonlinearSolveLayer, a NewtonCaps, a Rollout or a list of "
                        f"them (or a torch module holding them), got {got}")
    return found


def _is_solve_target(part) -> bool:
    try:
        return bool(as_target(part).layers)
    except TypeError:
        return False


def k_eps_of_counts(counts: list) -> int:
    """K_eps of plain layers from converged counts ``[(newton_steps or None, iterations), ...]``: the most
    Newton steps of the Newton layers, the most iterations of the linear ones (at least 1)."""
    steps = max((n for n, _ in counts if n is not None), default=0)
    iterations = max((k for n, k in counts if n is None), default=0)
    return max(1, steps, iterations)


@dataclasses.dataclass(frozen=True)
class LayerCaps:
    """Layers whose own cap is K: a linear layer's ``max_it``, a Newton layer's Newton cap (its inner cap
    stays as configured). ``call`` runs the target on keyword inputs (the layer itself, or a rollout)."""

    layers: tuple
    call: Callable | None = None
    converged = None

    @property
    def k(self) -> int | None:
        return self.layers[0].caps.max_it if self.layers else None

    @property
    def counts_newton_steps(self) -> bool:
        return any(layer.counts_newton_steps for layer in self.layers)

    def set_k(self, k: int) -> None:
        check_int("K", k, minimum=1)
        for layer in self.layers:
            layer.caps = dataclasses.replace(layer.caps, max_it=k)

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        saved = [layer.caps for layer in self.layers]
        try:
            yield
        finally:
            for layer, caps in zip(self.layers, saved):
                layer.caps = caps

    def k_eps_from(self, counts: list) -> int:
        return k_eps_of_counts(counts)

    def as_target(self) -> CapTarget:
        return self


class _NoLayers:
    """A target that moves no solve layer PRDP knows of."""

    layers: tuple = ()
    call = None
    counts_newton_steps = False
    converged = None

    def k_eps_from(self, counts: list) -> int:
        return k_eps_of_counts(counts)

    def as_target(self) -> CapTarget:
        return self


@dataclasses.dataclass(frozen=True)
class CapFunction(_NoLayers):
    """A function ``f(k)`` that moves the caps itself (PRDP calls it; what it moves is its own)."""

    function: Callable[[int], object]
    k = None

    def set_k(self, k: int) -> None:
        self.function(k)

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        yield


@dataclasses.dataclass(frozen=True)
class MaxItAttribute(_NoLayers):
    """An object whose cap is its ``max_it`` attribute (e.g. a SIP inverse's Gauss-Newton iterations)."""

    owner: object

    @property
    def k(self) -> int | None:
        return self.owner.max_it

    def set_k(self, k: int) -> None:
        self.owner.max_it = k

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        saved = self.owner.max_it
        try:
            yield
        finally:
            self.owner.max_it = saved


@dataclasses.dataclass(frozen=True)
class CapTargets:
    """Several targets moved together to one K (a list); none: nothing moves."""

    parts: tuple
    converged = None

    @property
    def layers(self) -> tuple:
        found: list = []
        for part in self.parts:
            found += [layer for layer in part.layers if not any(layer is seen for seen in found)]
        return tuple(found)

    @property
    def call(self) -> Callable | None:
        return self.parts[0].call if len(self.parts) == 1 else None

    @property
    def k(self) -> int | None:
        return self.parts[0].k if self.parts else None

    @property
    def counts_newton_steps(self) -> bool:
        return any(part.counts_newton_steps for part in self.parts)

    def set_k(self, k: int) -> None:
        for part in self.parts:
            part.set_k(k)

    @contextlib.contextmanager
    def kept(self) -> Iterator[None]:
        with contextlib.ExitStack() as stack:
            for part in self.parts:
                stack.enter_context(part.kept())
            yield

    def k_eps_from(self, counts: list) -> int:
        return self.parts[0].k_eps_from(counts) if len(self.parts) == 1 else k_eps_of_counts(counts)

    def as_target(self) -> CapTarget:
        return self
