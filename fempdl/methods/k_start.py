"""PRDP's first cap k0, measured where the loop runs: the smallest cap whose solve is not garbage.

PRDP refines K only when the validation metric stalls, so a k0 whose solve is
far from the solution trains the network on garbage before the metric can say
so (one Newton step from zero on a p-Laplacian: a first loss of 2.7e4, and a
model whose coefficient ended 1750% off). :func:`k_start` measures, on the
inputs and from the starts the loop uses (its ``initial_guess`` too), the
relative error of the capped solve against a converged one:

    e(K) = max over samples (and returned states) of ||u_K - u*|| / ||u*||   (owned DOFs, all ranks),

and returns the smallest K with e(K) <= ``tolerance`` (doubling K, then
bisecting: O(log K) capped solves).

The default tolerance follows what the network's gradient is at a capped
solve (:func:`default_tolerance`). Where it is the exact derivative of the
capped map (Richardson + Jacobi with right-hand-side controls, or unrolled
differentiation), a coarse cap trains the network on a coarse but consistent
physics that PRDP refines later: 0.5. Elsewhere (a Newton cap or a capped
Krylov solve differentiated implicitly, matrix controls) the gradient is the
implicit-function approximation at an unconverged state, wrong by about the
state's error, and Adam keeps early wrong gradients in its moments for hundreds
of steps: 0.01, which a fit to data needs anyway (a relative solution error e
moves a normalised misfit by about e^2, so a misfit of 1e-4 needs e near 1e-2). The target runs at each K with its caps,
counters and health state put back afterwards; the converged solves are its
layers' own solvers run to ``rtol`` (:func:`fempdl.layer.reference.converged_counts`'
twins). Any target PRDP moves works: a layer, a NewtonCaps, a Rollout, or a list
of layers with ``call=`` (a function returning the tensor(s) to compare).
"""
from __future__ import annotations

from collections.abc import Callable

import torch

from fempdl.core.checks import check_int, is_real
from fempdl.layer.cap_target import layers_target
from fempdl.layer.reference import converged_options, refuse_uncalled, routed, twin_of
from fempdl.methods.k_eps import left_as_is, measure_call
from fempdl.solve.stats import SolverFailedError

__all__ = ["k_start", "default_tolerance", "CONSISTENT_TOLERANCE", "IMPLICIT_TOLERANCE"]

#: k0's relative error where the capped gradient is the derivative of the capped map (module docstring).
CONSISTENT_TOLERANCE = 0.5
#: k0's relative error where it is the implicit-function approximation at an unconverged state.
IMPLICIT_TOLERANCE = 0.01


def default_tolerance(layers) -> float:
    """k0's default relative error for ``layers`` (module docstring): the looser one only when every layer's
    capped gradient is the derivative of the capped map."""
    return CONSISTENT_TOLERANCE if all(layer.exact_capped_gradient for layer in layers) else IMPLICIT_TOLERANCE


def k_start(target, *, tolerance: float | None = None, k_max: int = 100_000, rtol: float = 1e-8,
            call: Callable | None = None, **inputs) -> int:
    """The smallest cap K whose solves of ``inputs`` are within ``tolerance`` of converged solves.

    Args:
        target: what PRDP moves: a :class:`~fempdl.layer.solve_layer.SolveLayer`, a
            :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` (its Newton cap), a
            :class:`~fempdl.methods.newton_caps.NewtonCaps` (the cap its rule moves), a
            :class:`~fempdl.layer.rollout.Rollout`, or a list of layers (with ``call=``).
        tolerance: the largest acceptable relative error e(K), in (0, 1]; ``None``: by what the
            capped gradient is (:func:`default_tolerance`, module docstring).
        k_max: the largest K tried; if even it is not within ``tolerance``, ValueError.
        rtol: the converged reference's tolerance.
        call: instead of keyword inputs, a function that runs the target's layers as the loop does and
            returns the tensor (or tuple of tensors) to compare.
        inputs: the target's keyword inputs as the loop passes them ((B, n_m) or (n_m,)),
            ``initial_guess`` included for a warm-started loop.

    Example:
        ``ctrl = PRDP(layer, k0=k_start(layer, f=f_val), k_cap=k_eps(layer, f=f_val))``
    """
    target = layers_target(target)
    layers = list(target.layers)
    run = measure_call(target, call, inputs, "k0")
    if tolerance is None:
        tolerance = default_tolerance(layers)
    if not is_real(tolerance) or not 0.0 < tolerance <= 1.0:
        raise ValueError(f"tolerance must be a relative error in (0, 1], got {tolerance!r}")
    check_int("k_max", k_max, minimum=1)
    tolerance, k_max = float(tolerance), int(k_max)     # the K returned is a python int
    for layer in layers:
        if not layer.counts_newton_steps and layer.options.direct:
            raise ValueError(f"the layer solves directly (ksp_type={layer.options.ksp_type!r}): it has no "
                             "iteration cap to start")
    twins = [twin_of(layer, converged_options(layer, rtol)) for layer in layers]
    comm = layers[0].problem.V.mesh.comm
    try:
        with torch.no_grad(), left_as_is(target):
            with routed(zip(layers, twins)):
                reference = _tensors(run())
            refuse_uncalled(twins)
            if not all(isinstance(u, torch.Tensor) for u in reference):
                raise TypeError("call must return the tensor (or tuple of tensors) to compare, got "
                                f"{', '.join(type(u).__name__ for u in reference)}")

            def error(k: int) -> float:
                target.set_k(k)
                try:
                    return max(_relative_error(u, ref, comm) for u, ref in zip(_tensors(run()), reference))
                except SolverFailedError:          # a capped solve that broke down is garbage too
                    return float("inf")

            low, high = 0, 1           # error(low) > tolerance (low = 0: no solve), error(high) to test
            while error(high) > tolerance:
                if high >= k_max:
                    raise ValueError(f"no cap up to k_max={k_max} brings these solves within a relative error of "
                                     f"{tolerance} of converged ones; raise k_max or tolerance, or check the solver")
                low, high = high, min(2 * high, k_max)
            while high - low > 1:
                mid = (low + high) // 2
                low, high = (low, mid) if error(mid) <= tolerance else (mid, high)
            return high
    finally:
        for twin in twins:
            twin.close()


def _tensors(out) -> tuple:
    return tuple(out) if isinstance(out, (tuple, list)) else (out,)


def _relative_error(u: torch.Tensor, reference: torch.Tensor, comm) -> float:
    """max over samples of ||u - ref|| / ||ref|| over every rank's owned DOFs (inf where u is not finite)."""
    u, reference = u.reshape(-1, u.shape[-1]), reference.reshape(-1, reference.shape[-1])
    sums = torch.stack([((u - reference) ** 2).sum(1), (reference ** 2).sum(1)]).numpy()
    if comm.size > 1:
        sums = comm.allreduce(sums)
    errors = torch.from_numpy(sums[0] / sums[1].clip(min=1e-300)).sqrt()
    return float(errors.nan_to_num(nan=float("inf")).max())
