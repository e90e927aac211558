"""Reference physics: a layer's calls answered by a converged twin on the same problem.

A network trained through capped solves can learn the cap's bias: a source f
that only the K-sweep solver maps to the right u. A validation metric computed
with those same capped solves cannot see it. What a trained model is used with
is converged physics, so that is what judges it:

* :func:`reference_physics` (``with reference_physics(layer): metric = ...``)
  sends each call of the given layers to its *reference twin*, a layer of the
  same class on the same problem that solves converged: LU where it fits, else
  the converged iterative default (:func:`~fempdl.solve.default_solver.default_options`);
  for a Newton layer, Newton to its tolerance (at most 1e-8) with that inner
  solve, or its own inner solve where that is direct. The twin is built on the
  first reference call and kept (its factorisations too); its counters are the
  layer's ``reference_stats``, apart from ``stats``, the training cost.
* :func:`converged_counts` runs a callable with the layers' calls sent to
  twins that solve converged *with the layers' own solver* (to ``rtol``) and
  returns what those solves needed: the iterations (and Newton steps) a cap
  must allow, K_eps, at the inputs the callable passes (a Rollout's states, a
  validation set at the current model).

Calls are routed in the layer's ``forward`` (and in a scheduled rollout's plan),
so whatever calls the layer (a Rollout, a user's model) calls the twin. Routing
is per layer and undone on exit; nothing else about the layer changes.
"""
from __future__ import annotations

import copy
import dataclasses
from collections.abc import Callable, Iterable
from contextlib import contextmanager

import torch

from fempdl.layer.cap_target import layers_target
from fempdl.layer.newton_layer import NonlinearSolveLayer
from fempdl.layer.solve_layer import SolveLayer
from fempdl.layer.system_layer import SystemLayer
from fempdl.solve.default_solver import default_options

__all__ = ["reference_physics", "routed", "converged_counts", "refuse_uncalled", "reference_options",
           "converged_options", "twin_of", "counters_kept", "REFERENCE_NEWTON_RTOL"]

#: The loosest Newton tolerance a reference twin takes (a layer's own, if tighter).
REFERENCE_NEWTON_RTOL = 1e-8


def reference_options(layer: SystemLayer):
    """The options of ``layer``'s reference twin (module docstring)."""
    options = layer.options
    if isinstance(layer, NonlinearSolveLayer):
        ksp = options.ksp if options.ksp.direct else default_options(layer.problem)
        return dataclasses.replace(options, max_it=None, rtol=min(options.rtol, REFERENCE_NEWTON_RTOL), ksp=ksp,
                                   on_failure="raise")
    if options.direct:
        return dataclasses.replace(options, adjoint=None, options_prefix=None)
    return default_options(layer.problem)


def converged_options(layer: SystemLayer, rtol: float):
    """``layer``'s own solver run to ``rtol`` (no cap): what K_eps is measured with."""
    options = layer.options
    if isinstance(layer, NonlinearSolveLayer):
        ksp = options.ksp
        inner = ksp if ksp.direct else dataclasses.replace(ksp, max_it=None, rtol=rtol, atol=None, divtol=None,
                                                            adjoint=None, engine="petsc", options_prefix=None)
        return dataclasses.replace(options, max_it=None, rtol=rtol, ksp=inner)
    if options.direct:
        raise ValueError(f"layer solves directly (ksp_type={options.ksp_type!r}): it has no iteration cap")
    return dataclasses.replace(options, max_it=None, rtol=rtol, atol=None, divtol=None, adjoint=None,
                               engine="petsc", options_prefix=None)


def twin_of(layer: SystemLayer, options) -> SystemLayer:
    """A layer of ``layer``'s class on its problem, with ``options`` (the caller closes it)."""
    if not isinstance(layer, (SolveLayer, NonlinearSolveLayer)):
        raise TypeError(f"reference physics needs SolveLayers or NonlinearSolveLayers, got {type(layer).__name__}")
    return type(layer)(layer.problem, options)


@contextmanager
def routed(pairs: Iterable[tuple[SystemLayer, SystemLayer]]):
    """Within the block, each call of a layer is answered by its twin (pairs of (layer, twin))."""
    pairs = list(pairs)
    before = [layer.route for layer, _ in pairs]
    for layer, twin in pairs:
        layer.route = twin
    try:
        yield
    finally:
        for (layer, _), previous in zip(pairs, before):
            layer.route = previous


@contextmanager
def reference_physics(layers):
    """Within the block, ``layers`` (a layer or an iterable of them) solve at reference physics
    (module docstring); their ``stats`` do not move, their ``reference_stats`` count the solves.

    Example:
        >>> with torch.no_grad(), reference_physics(layer):
        ...     metric = nmse(layer(f=net(z_val)), u_val)       # the model as it is deployed
    """
    # A rollout's step layer, the layers inside a module or a list.
    layers = [layers] if isinstance(layers, SystemLayer) else list(layers_target(layers, "the layers").layers)
    twins = []
    for layer in layers:
        if layer.reference_twin is None:
            layer.reference_twin = twin_of(layer, reference_options(layer))
        twins.append(layer.reference_twin)
    with routed(zip(layers, twins)):
        yield


def converged_counts(layers: list, run: Callable[[], object], rtol: float) -> list[tuple[int | None, int]]:
    """Per layer, (most Newton steps, most inner iterations of a solve or step) that ``run()`` needed with
    each layer's calls solved converged by its own solver to ``rtol`` (Newton steps None for a linear
    layer; 0 where the layer was not called). Runs without gradients; the layers are left as they are."""
    twins = [twin_of(layer, converged_options(layer, rtol)) for layer in layers]
    try:
        with torch.no_grad(), routed(zip(layers, twins)):
            run()
        refuse_uncalled(twins)
        return [(getattr(twin.stats, "max_newton_steps", None), twin.stats.max_forward_iterations)
                for twin in twins]
    finally:
        for twin in twins:
            twin.close()


def refuse_uncalled(twins: list) -> None:
    """Refuse a measurement whose call solved with none of the target's layers (routed to ``twins``): counts
    or errors of nothing would read as a cap of 1 (the call went to other layer objects, or nowhere)."""
    if twins and not any(twin.stats.forward_solves for twin in twins):
        raise ValueError(f"the call did not solve with the target: none of its {len(twins)} layer(s) was called "
                         "(a call through another layer object, or one that solves nothing); pass a function that "
                         "calls the target's own layers")


@contextmanager
def counters_kept(layers):
    """Leave the solves run inside out of ``layers``' counters (``stats``, in place: the system holds the
    same object, and ``capped_eval_calls``); the wall clock still sees the time."""
    layers = list(layers)
    saved = [(copy.deepcopy(layer.stats), layer.capped_eval_calls) for layer in layers]
    try:
        yield
    finally:
        for layer, (before, calls) in zip(layers, saved):
            for f in dataclasses.fields(before):
                setattr(layer.stats, f.name, getattr(before, f.name))
            layer.capped_eval_calls = calls
