"""A solve layer's health check: its capped training calls solved again at a refined cap while garbage.

PRDP installs a :class:`~fempdl.solve.health.HealthCheck` on the layers it
moves. :class:`HealthyCalls` is what a layer does with it, for its forward
solves and for the adjoint solves of their backward alike: a training call's
capped solves measure their residual ratio rho = ||r_K|| / ||r_0|| (the
forward's r = b - A x, the adjoint's r = dJ/du - A^T lam); above the limit
the check's ``refine`` raises the caps and the call is solved again, before
anything downstream sees the garbage.

The adjoint matters on its own: a left-preconditioned GMRES can leave a
forward state within 0.5% while the adjoint of the same cap, whose
right-hand side (a misfit at a few sensors) is far rougher, ends with its
residual at twice its start, and the gradient then points anywhere
(benchmarks/bench_prdp_loops.py, ``stokes-inverse``). An adjoint solved
again at the refined cap is the implicit gradient at the forward's state
with a sound adjoint. Where the gradient is that implicit approximation
(capped Krylov solves, matrix controls), its error is about the adjoint's, so
an adjoint must shrink its residual to the check's ``adjoint_limit`` (PRDP's
``adjoint_health``, 1%), not merely shrink it: the same 1% as k0's default
tolerance for such layers (:mod:`fempdl.methods.k_start`).

Measured are the first training call at new caps and every ``HEALTH_EVERY``-th
after, forward and adjoint counted apart (the same calls on every rank: the
caps agree and training calls run in step).

Without a check (a plain call, outside PRDP) a layer whose capped forward
solve is a stationary iteration (Richardson, Chebyshev: ``watched``) still
measures its first call at each cap and warns when the residual grew: such an
iteration diverges where its iteration matrix has a spectral radius above 1
(Jacobi on P2 elements or on sliver cells), and its result is then no coarse
solution but garbage. Krylov methods are not watched: CG and GMRES minimise a
norm of the error or of the (preconditioned) residual, which a capped run
bounds by its start.
"""
from __future__ import annotations

import math
from collections.abc import Callable

from fempdl.core.ranks import torch_group_initialised, training_ranks
from fempdl.solve.caps import Caps
from fempdl.solve.health import CallHealth, HealthCheck
from fempdl.solve.stats import SolverWarning, warn_at_caller

__all__ = ["HealthyCalls", "HEALTH_EVERY", "MAX_HEALTH_REFINES", "DIRECTIONS"]

#: Refinements one call may ask for (each raises the cap; a refinement that does not lower the ratio ends them).
MAX_HEALTH_REFINES = 100
#: A health check measures the first training call at new caps and then every HEALTH_EVERY-th: garbage comes
#: from a cap too small for the inputs, which a new cap's first call shows and inputs drifting over training
#: show within a few calls; measuring every call would cost a loop whose solves are cheap several percent.
HEALTH_EVERY = 8
#: A residual ratio above this is growth: a plain call's stationary iteration diverges.
DIVERGING = 1.0
#: The solves a check measures: a call's forward solves and its backward's adjoint solves.
DIRECTIONS = ("forward", "adjoint")


class HealthyCalls:
    """One layer's health check and what it measured (module docstring).

    Args:
        name: the layer's kind, for warnings.
        distributed: whether the layer's mesh is distributed (its norms are global already).
        stats: the system's :class:`~fempdl.solve.stats.CumulativeStats` (a plain call's failed solve has
            said so: no second warning).
    """

    def __init__(self, name: str, distributed: bool, stats=None):
        self.name, self._distributed, self._stats = name, distributed, stats
        self._watched_caps: set[Caps] = set()                # caps a plain call has measured at
        self.check: HealthCheck | None = None
        self._due = dict.fromkeys(DIRECTIONS, (None, 0))     # (caps of the last measured call, calls since)
        #: The largest residual ratio of the last measured call, by direction (None: none yet).
        self.last_ratio: dict[str, float | None] = dict.fromkeys(DIRECTIONS)

    def install(self, check: HealthCheck | None) -> None:
        if check is not None and not isinstance(check, HealthCheck):
            raise TypeError(f"health must be a fempdl.solve.health.HealthCheck or None, got {type(check).__name__}")
        self.check, self._due = check, dict.fromkeys(DIRECTIONS, (None, 0))

    def run(self, solve: Callable[[CallHealth | None], object], caps: Callable[[], Caps], training: bool,
            direction: str = "forward", exact: bool = True, watched: bool = False):
        """``solve(health)``, one call's solves, which measure their residual ratios into ``health`` (a fresh
        :class:`CallHealth`, or ``None``: measure nothing), run again at a refined cap while a training
        call's capped solves are garbage (their largest ratio above the limit, agreed over the ranks that
        train together). A no-grad call (validation) is never refined: it trains nothing, and a validation
        that one rank runs alone must not enter a collective. Refinement ends when the ratio is within the
        limit, when the caps cannot rise, or when a refinement did not lower the ratio (a diverging
        iteration: more of it does not help); the last two warn and keep the solve. ``caps()``: the layer's
        caps now; ``exact``: its capped gradient is the derivative of the capped map (else an adjoint has the
        check's adjoint limit); ``watched``: without a check, measure the first call at each cap and warn when
        its residual grew (module docstring)."""
        check = self.check
        if check is None and direction == "forward" and watched and caps() not in self._watched_caps:
            return self._watch(solve, caps())
        if check is None or not training or not self._is_due(direction, caps()):
            return solve(None)
        limit = check.limit_for(direction, exact)
        previous = math.inf
        for _ in range(MAX_HEALTH_REFINES):
            measured = CallHealth(limit)
            result = solve(measured)
            ratio = self.last_ratio[direction] = self._agreed(measured.ratio)
            self._due[direction] = (caps(), 1)
            if ratio is None or ratio <= limit:
                return result
            if ratio >= previous:
                why = (f"refining did not lower it (from {previous:.3g}): the iteration diverges at these inputs; "
                       "use a convergent solver or preconditioner")
                break
            if not check.refine(ratio):
                why = "the cap cannot rise further (k_cap): raise k_cap or use a stronger solver"
                break
            previous = ratio
        else:
            why = f"{MAX_HEALTH_REFINES} refinements did not cure it"
        what = "solve" if direction == "forward" else "adjoint solve"
        warn_at_caller(f"a capped {what} of this {self.name} ends with its residual at {ratio:.3g} times its start "
                       f"(health limit {limit:g}) at {caps()}, and {why}; the network trains on that "
                       "solve", SolverWarning)
        return result

    def _watch(self, solve: Callable[[CallHealth | None], object], caps: Caps):
        """A plain call's capped stationary solves, measured; a warning when their residual grew."""
        measured = CallHealth(DIVERGING)
        failures = None if self._stats is None else self._stats.failures
        result = solve(measured)
        self._watched_caps.add(caps)
        reported = failures is not None and self._stats.failures > failures     # the failure said it already
        if measured.ratio is not None and measured.ratio > DIVERGING and not reported:
            warn_at_caller(f"a capped solve of this {self.name} ends with its residual at {measured.ratio:.3g} times "
                           f"its start at {caps}: the iteration diverges for this operator (its iteration "
                           "matrix has a spectral radius above 1, e.g. Jacobi on P2 elements or sliver cells), so "
                           "the result is no coarse solution; use CG or GMRES, or damp it "
                           "(petsc_options={'ksp_richardson_scale': 0.5})", SolverWarning)
        return result

    def schedule(self) -> dict:
        """When the next calls are measured, by direction: [caps of the last measured call (max_it,
        inner_max_it) or None, calls since]; saved with PRDP's state, so a resumed run measures the calls
        the uninterrupted one measures."""
        return {d: [None if caps is None else [caps.max_it, caps.inner_max_it], since]
                for d, (caps, since) in self._due.items()}

    def load_schedule(self, saved: dict) -> None:
        """Restore :meth:`schedule`'s value."""
        if set(saved) != set(DIRECTIONS):
            raise ValueError(f"a saved health schedule has directions {sorted(saved)}, not {list(DIRECTIONS)}")
        self._due = {d: (None if caps is None else Caps(*caps), int(since)) for d, (caps, since) in saved.items()}

    def _is_due(self, direction: str, now: Caps) -> bool:
        caps, since = self._due[direction]
        if caps == now and since % HEALTH_EVERY:
            self._due[direction] = (caps, since + 1)
            return False
        return True

    def _agreed(self, ratio: float | None) -> float | None:
        """The largest ratio over the ranks of a torch.distributed group (each holds its own data shard, so
        they decide together); a distributed mesh's norms are global already."""
        if self._distributed or not torch_group_initialised():
            return ratio
        ranks = training_ranks()
        if ranks is None:
            return ratio
        largest = ranks.max(-1.0 if ratio is None else ratio)      # -1: no capped solve measured
        return None if largest < 0.0 else largest
