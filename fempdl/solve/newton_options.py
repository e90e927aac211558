"""NewtonOptions: an immutable, validated description of a (possibly capped) Newton solve of F(u) = 0.

Two caps, as for a linear solve (:class:`~fempdl.solve.options.KSPOptions`):

* the Newton cap ``max_it=N``: a budget of N Newton steps where the system is built as one (a layer
  with implicit gradients: it stops at ``rtol``/``atol`` or the round-off floor first,
  :mod:`fempdl.solve.newton_stop`); otherwise exactly N Newton steps from the initial guess
  (the step's tolerances are off: rtol = atol = 0, no step-length test); it
  stops earlier only if the residual vanishes exactly, or if a line search or
  trust region cannot decrease a residual that already meets ``rtol``/``atol``
  (the solution, reported as converged: a cap that PRDP raised past
  convergence returns the solution). ``max_it=None`` runs to
  ``rtol``/``atol`` and not reaching them in ``converged_max_it`` steps, or any
  other stop of PETSc's SNES (a failed line search, a NaN), is a failure that
  names SNES's reason;
* the inner cap: ``ksp`` is the :class:`KSPOptions` of each step's linear solve
  J(u_k) du = F(u_k), capped (``max_it=K``: K Krylov iterations per step) or
  converged, any preset.

What ``rtol`` is relative to (:func:`rtol_scale`): the smaller of ||F(u_0)|| and ||F(u_ref)||, u_ref
the zero state with the boundary values put in (the start of a solve from zero; its residual is the
load's scale, what DOLFINx's Newton from a zero guess measures against). Relative to ||F(u_0)|| alone
the test is only as good as the start: a warm start far from the solution has a huge residual (it
grows as a power of the guess where F does), and rtol of that accepts a state still far from the
solution. The smaller of the two is not fooled by a far start, still holds a warm start near its
solution to its own rtol (there ||F(u_0)|| is the smaller), and costs one residual assembly per solve
with an ``initial_guess`` (none from zero, where u_0 = u_ref). A NaN or inf residual at u_ref is no
scale: then ||F(u_0)|| alone.

Methods (``snes_type``): ``"newton"`` (the default), plain Newton:
u_{k+1} = u_k - damping * J(u_k)^{-1} F(u_k) (``newtonls`` with the full-step
``"basic"`` line search scaled by ``damping``; DOLFINx's NewtonSolver does the
same), ``"newtonls"`` (PETSc's line-search Newton, backtracking ``"bt"`` unless
``linesearch`` says otherwise) and ``"newtontr"`` (trust region). Plain Newton
is the default because a line search helps only far from the solution and can
crawl on stiff problems (on a slender neo-Hookean beam backtracking took 33
steps where plain Newton took 8); when plain Newton diverges, try ``"newtonls"``
or load increments with ``initial_guess=``. The unrolled derivative is that of
plain Newton's map, whose steps do not depend on a line search's choices.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from fempdl.core.checks import check_int, is_real, python_number
from fempdl.solve.options import MAX_PETSC_INT, KSPOptions

__all__ = ["NewtonOptions", "SNES_TYPES", "LINE_SEARCHES", "DEFAULT_NEWTON_RTOL", "DEFAULT_NEWTON_ATOL",
           "rtol_scale"]

SNES_TYPES = ("newtonls", "newtontr", "newton")
LINE_SEARCHES = ("bt", "basic", "l2", "cp")
DEFAULT_NEWTON_RTOL = 1e-10
DEFAULT_NEWTON_ATOL = 1e-12


def rtol_scale(initial: float, reference: float | None = None) -> float:
    """What ``rtol`` is relative to (module docstring): min(||F(u_0)||, ||F(u_ref)||), ``initial`` alone
    when the reference was not measured (``None``: a start from zero, where u_0 = u_ref) or is not finite."""
    if reference is None or not math.isfinite(reference):
        return initial
    return min(initial, reference)


@dataclass(frozen=True)
class NewtonOptions:
    """Options of a (possibly capped) Newton solve; see the module docstring.

    Args:
        max_it: the Newton cap N (int >= 1): exactly N steps. ``None``: run to
            the tolerances, a failure if they are not met.
        rtol: relative residual tolerance ||F(u_k)|| <= rtol min(||F(u_0)||, ||F(u_ref)||), u_ref the zero
            state with the boundary values (:func:`rtol_scale`; solves that stop at their tolerances).
        atol: absolute residual tolerance ||F(u_k)|| <= atol (uncapped solves).
        snes_type: ``"newton"`` (plain, full steps: DOLFINx's NewtonSolver; the default),
            ``"newtonls"`` (a line search) or ``"newtontr"`` (a trust region).
        linesearch: ``"bt"`` (default of ``newtonls``), ``"basic"``, ``"l2"`` or ``"cp"``;
            only for ``newtonls``.
        damping: the step length of plain Newton (0 < damping <= 1).
        ksp: the inner linear solve: :class:`KSPOptions` or a preset name; capped
            or converged. ``None`` lets the layer choose (LU where it fits).
        converged_max_it: the most steps an uncapped solve may take.
        on_failure: ``"raise"`` (:class:`~fempdl.solve.stats.SolverFailedError`)
            or ``"warn"`` (the last iterate with a finite residual, with a warning) when
            Newton fails. The adjoint's transposed solve follows ``ksp.on_failure``.
    """

    max_it: int | None = None
    rtol: float = DEFAULT_NEWTON_RTOL
    atol: float = DEFAULT_NEWTON_ATOL
    snes_type: str = "newton"
    linesearch: str | None = None
    damping: float = 1.0
    ksp: KSPOptions | str | None = None
    converged_max_it: int = 50
    on_failure: str = "raise"

    def __post_init__(self):
        if self.max_it is not None:
            check_int("NewtonOptions.max_it", self.max_it, minimum=1, maximum=MAX_PETSC_INT,
                      hint="the number of Newton steps, or None to run to rtol/atol")
        check_int("NewtonOptions.converged_max_it", self.converged_max_it, minimum=1, maximum=MAX_PETSC_INT)
        for name in ("rtol", "atol"):
            value = getattr(self, name)
            if not is_real(value) or not 0 <= value < 1 or not math.isfinite(value):
                raise ValueError(f"NewtonOptions.{name} must be a number in [0, 1), got {value!r}")
        if self.max_it is None and self.rtol == 0 and self.atol == 0:
            raise ValueError("an uncapped Newton solve (max_it=None) needs rtol > 0 or atol > 0")
        if self.snes_type not in SNES_TYPES:
            raise ValueError(f"NewtonOptions.snes_type must be one of {list(SNES_TYPES)}, got {self.snes_type!r}")
        if self.linesearch is not None:
            if self.linesearch not in LINE_SEARCHES:
                raise ValueError(f"NewtonOptions.linesearch must be one of {list(LINE_SEARCHES)}, "
                                 f"got {self.linesearch!r}")
            if self.snes_type != "newtonls":
                raise ValueError(f"a line search applies to snes_type='newtonls', not {self.snes_type!r}")
        if not is_real(self.damping) or not 0 < self.damping <= 1:
            raise ValueError(f"NewtonOptions.damping must be in (0, 1], got {self.damping!r}")
        # Numpy scalars are stored as python numbers: options are compared and printed.
        for name in ("max_it", "converged_max_it", "rtol", "atol", "damping"):
            object.__setattr__(self, name, python_number(getattr(self, name)))
        if self.damping != 1 and self.snes_type != "newton":
            raise ValueError("damping applies to plain Newton (snes_type='newton')")
        if isinstance(self.ksp, str):
            object.__setattr__(self, "ksp", KSPOptions.preset(self.ksp))
        elif self.ksp is not None and not isinstance(self.ksp, KSPOptions):
            raise TypeError(f"NewtonOptions.ksp must be KSPOptions, a preset name or None, "
                            f"got {type(self.ksp).__name__}")
        if self.ksp is not None and self.ksp.lag_preconditioner and self.ksp.direct:
            raise ValueError("a Newton solve's lagged preconditioner (KSPOptions.lag_preconditioner) needs a Krylov "
                             "inner solve run to a tolerance, e.g. KSPOptions.preset('lu-lagged'): with "
                             "ksp_type='preonly' every step would solve an earlier Jacobian, not its own")
        if self.on_failure not in ("raise", "warn"):
            raise ValueError(f"NewtonOptions.on_failure must be 'raise' or 'warn', got {self.on_failure!r}")

    @property
    def capped(self) -> bool:
        """Whether the Newton solve runs exactly ``max_it`` steps."""
        return self.max_it is not None

    @property
    def step_limit(self) -> int:
        """The most Newton steps a solve may take."""
        return self.converged_max_it if self.max_it is None else self.max_it

    @property
    def plain(self) -> bool:
        """Whether every step is the full (or fixed-damping) Newton step, with no line search's choice."""
        return self.snes_type == "newton" or (self.snes_type == "newtonls" and self.linesearch == "basic")

    def snes_tolerances(self) -> dict:
        """Keyword arguments of ``SNES.setTolerances``: zero tolerances under a cap."""
        if self.capped:
            return dict(rtol=0.0, atol=0.0, stol=0.0, max_it=self.max_it)
        return dict(rtol=self.rtol, atol=self.atol, stol=0.0, max_it=self.converged_max_it)

    def tolerances_met(self, residual_norms, reference: float | None = None) -> bool:
        """Whether the last of ||F(u_0)||, ..., ||F(u_k)|| meets the uncapped tolerances: ``atol``, or
        ``rtol`` relative to :func:`rtol_scale` of the first and ``reference`` (||F(u_ref)||, ``None``
        for a start from zero), the rule the solve's stop test applied."""
        return bool(residual_norms) and math.isfinite(residual_norms[-1]) and (
            residual_norms[-1] <= self.rtol * rtol_scale(residual_norms[0], reference)
            or residual_norms[-1] <= self.atol)

    def with_max_it(self, max_it: int | None) -> NewtonOptions:
        """A copy with the Newton cap moved."""
        return dataclasses.replace(self, max_it=max_it)

    def with_inner_max_it(self, max_it: int | None) -> NewtonOptions:
        """A copy with the inner (linear) cap moved."""
        if self.ksp is None:
            raise ValueError("the inner solve's options are not set yet (ksp=None); give NewtonOptions(ksp=...)")
        return dataclasses.replace(self, ksp=self.ksp.with_max_it(max_it))
