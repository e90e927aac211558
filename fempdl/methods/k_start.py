"""PRDP's first cap k0, measured where the loop runs: the smallest cap whose solve is not garbage.

PRDP refines K only when the validation metric stalls, so a k0 whose solve is
far from the solution trains the network on garbage before the metric can say
so (one Newton step from zero on a p-Laplacian: a first loss of 2.7e4, and a
model whose coefficient ended 1750% off). :func:`k_start` measures, on the
inputs and from the starts the loop uses (its ``initial_guess`` too), the
relative error of the capped solve against a converged one:

    e(K) = max over samples of ||u_K - u*|| / ||u*||   (owned DOFs, all ranks),

and returns the smallest K with e(K) <= ``tolerance`` (doubling K, then
bisecting: O(log K) capped solves). Probe layers on the same problem do the
solves, so the target's caps and counters are left as they are.
"""
from __future__ import annotations

import dataclasses

import torch

from fempdl.core.checks import check_int
from fempdl.layer.newton_layer import NonlinearSolveLayer
from fempdl.layer.solve_layer import SolveLayer
from fempdl.methods.newton_caps import NewtonCaps
from fempdl.solve.stats import SolverFailedError

__all__ = ["k_start", "probe_layers", "close_probes"]


def k_start(target, *, tolerance: float = 0.5, k_max: int = 100_000, rtol: float = 1e-8, **inputs) -> int:
    """The smallest cap K whose solves of ``inputs`` are within ``tolerance`` of converged solves.

    Args:
        target: a :class:`~fempdl.layer.solve_layer.SolveLayer`, a
            :class:`~fempdl.layer.newton_layer.NonlinearSolveLayer` (its Newton cap), or a
            :class:`~fempdl.methods.newton_caps.NewtonCaps` (the cap its rule moves): what PRDP moves.
        tolerance: the largest acceptable relative error e(K) (module docstring), in (0, 1].
        k_max: the largest K tried; if even it is not within ``tolerance``, ValueError.
        rtol: the converged reference's tolerance.
        inputs: the layer's keyword inputs as the loop passes them ((B, n_m) or (n_m,)),
            ``initial_guess`` included for a warm-started loop.

    Example:
        ``ctrl = PRDP(layer, k0=k_start(layer, f=f_val), k_cap=k_eps(layer, f=f_val))``
    """
    if not inputs:
        raise ValueError("give the inputs to measure k0 on as keyword arguments (those the loop passes, "
                         "initial_guess included if it warm-starts)")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float)) or not 0.0 < tolerance <= 1.0:
        raise ValueError(f"tolerance must be a relative error in (0, 1], got {tolerance!r}")
    check_int("k_max", k_max, minimum=1)
    capped, converged = probe_layers(target, rtol)
    try:
        with torch.no_grad():
            reference = converged(**inputs)
            comm = converged.problem.V.mesh.comm

            def error(k: int) -> float:
                capped.max_it = k
                try:
                    return _relative_error(capped(**inputs), reference, comm)
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
        close_probes(capped, converged)


def probe_layers(target, rtol: float = 1e-8):
    """Probe layers on ``target``'s problem: a capped one that takes K as ``max_it`` (a layer, or a
    NewtonCaps over one, moved by the target's rule) and a converged one (to ``rtol``). The caller
    closes them (``close_probes``)."""
    if isinstance(target, NonlinearSolveLayer):
        target = NewtonCaps(target, "newton")
    if isinstance(target, NewtonCaps):
        layer = target.layers[0]
        probe = NewtonCaps(NonlinearSolveLayer(layer.problem, layer.options), target.refine,
                           inner_per_k=target.inner_per_k)
        probe.converged = target.converged
        ksp = layer.options.ksp
        inner = ksp if ksp.direct else dataclasses.replace(ksp, max_it=None, rtol=rtol, atol=None, divtol=None,
                                                            adjoint=None)
        reference = NonlinearSolveLayer(layer.problem, dataclasses.replace(layer.options, max_it=None, rtol=rtol,
                                                                           ksp=inner))
        return _Caller(probe), reference
    if isinstance(target, SolveLayer):
        if target.options.direct:
            raise ValueError(f"the layer solves directly (ksp_type={target.options.ksp_type!r}): it has no "
                             "iteration cap to start")
        options = dataclasses.replace(target.options, adjoint=None, options_prefix=None)
        converged = dataclasses.replace(options, max_it=None, rtol=rtol, atol=None, divtol=None)
        return SolveLayer(target.problem, options), SolveLayer(target.problem, converged)
    raise TypeError(f"target must be a SolveLayer, a NonlinearSolveLayer or a NewtonCaps, got {type(target).__name__}")


def close_probes(capped, converged) -> None:
    for layer in (*getattr(capped, "layers", [capped]), converged):
        layer.close()


class _Caller:
    """A NewtonCaps over one probe layer, callable like the layer (K set through the caps' rule)."""

    def __init__(self, caps: NewtonCaps):
        self.caps, self.layers = caps, caps.layers

    @property
    def max_it(self):
        return self.caps.max_it

    @max_it.setter
    def max_it(self, k: int) -> None:
        self.caps.max_it = k

    def __call__(self, **inputs):
        return self.layers[0](**inputs)


def _relative_error(u: torch.Tensor, reference: torch.Tensor, comm) -> float:
    """max over samples of ||u - ref|| / ||ref|| over every rank's owned DOFs (inf where u is not finite)."""
    u, reference = u.reshape(-1, u.shape[-1]), reference.reshape(-1, reference.shape[-1])
    sums = torch.stack([((u - reference) ** 2).sum(1), (reference ** 2).sum(1)]).numpy()
    if comm.size > 1:
        sums = comm.allreduce(sums)
    errors = torch.from_numpy(sums[0] / sums[1].clip(min=1e-300)).sqrt()
    return float(errors.nan_to_num(nan=float("inf")).max())
