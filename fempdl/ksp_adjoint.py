"""Capped PETSc Krylov solves, their transposes, and iteration accounting.

This module knows PETSc and nothing of UFL or torch. It has three parts:

* :class:`KSPOptions` — an immutable, validated description of a linear solver
  (KSP type, preconditioner, iteration cap, tolerances, extra PETSc options, and
  an optional override for the adjoint solve). Presets: ``"jacobi"``
  (Richardson + PCJACOBI), ``"cg"``, ``"gmres"``, ``"lu"``.
* :class:`CappedSolver` — a KSP on one operator with ``solve`` (A x = b) and
  ``solve_transpose`` (A^T x = b), each returning a :class:`SolveStats`.
* :class:`CumulativeStats` — forward/backward iteration and time counters; the
  sum ``forward_iterations + backward_iterations`` is the cost metric PRDP
  savings are quoted in.

Semantics of a capped solve (``max_it`` set): it starts from a zero initial
guess (or from a given one: a warm start) and runs exactly ``max_it`` iterations, never more. It stops earlier only
if the user asked for a tolerance (``rtol``/``atol``) and it is met, or if the
residual vanishes exactly. Without ``rtol`` the convergence test is effectively
disabled (rtol = atol = 0, no divergence test), and Richardson/CG/Chebyshev skip
computing the residual norm altogether (PETSc's NORM_NONE), which is 15-25%
faster; ``SolveStats.residual_norm`` is then ``None``.

With ``max_it=None`` a solve runs to ``rtol`` (default 1e-10) and not reaching it
is a failure.
"""
from __future__ import annotations

import dataclasses
import itertools
import math
import re
import sys
import time
import types
import warnings
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np
from petsc4py import PETSc

__all__ = [
    "KSPOptions",
    "CappedSolver",
    "SolveStats",
    "CumulativeStats",
    "SolverFailedError",
    "SolverWarning",
    "PRESETS",
    "petsc_to_scipy",
]

_KSP_TYPES = frozenset(getattr(PETSc.KSP.Type, n) for n in dir(PETSc.KSP.Type) if n.isupper())
_PC_TYPES = frozenset(getattr(PETSc.PC.Type, n) for n in dir(PETSc.PC.Type) if n.isupper())
_REASON_NAMES = {
    getattr(PETSc.KSP.ConvergedReason, n): n
    for n in dir(PETSc.KSP.ConvergedReason)
    if n.isupper() and not n.startswith("CONVERGED_ITERATING")
}
_DIVERGED_MAX_IT = PETSc.KSP.ConvergedReason.DIVERGED_MAX_IT
_DIVERGED_BREAKDOWN = PETSc.KSP.ConvergedReason.DIVERGED_BREAKDOWN
# A breakdown with the residual below this fraction of ||b|| is GMRES's happy
# breakdown under a pure cap (tolerance 0): the Krylov space holds the solution.
_HAPPY_BREAKDOWN = 1e-12
_RESTARTED_KSP_TYPES = frozenset({"gmres", "fgmres", "lgmres", "dgmres", "pgmres", "pipefgmres"})
# Methods whose iteration does not need the residual norm: with a pure cap they
# run with NORM_NONE (no reduction per iteration).
_NORM_FREE_KSP_TYPES = frozenset({"richardson", "cg", "chebyshev"})
_DIRECT_KSP_TYPES = frozenset({"preonly"})
# Preconditioners that solve the system exactly (a factorisation): only with one of
# them is a single application (KSPPREONLY) a direct solve.
_FACTORISING_PC_TYPES = frozenset({"lu", "cholesky", "qr", "svd", "redundant"})
# PETSc's largest int in this build (32- or 64-bit indices): larger caps overflow inside PETSc.
MAX_PETSC_INT = int(np.iinfo(PETSc.IntType).max)
# Solves whose cap (DEFAULT_CONVERGED_MAX_IT when uncapped) times the number of
# unknowns reaches this get a Python KSP monitor, so that Ctrl-C (a pending
# KeyboardInterrupt) stops them within an iteration. That is about 0.3 s of
# Richardson-Jacobi iterations or more; the monitor's call costs 0.2-0.7 us per
# iteration (scripts/bench_bounds.py), which only matters for small, short solves,
# and those go without it.
INTERRUPT_CHECK_MIN_WORK = 10 ** 8
# Keys that have a first-class field; setting them through petsc_options would
# silently fight the cap that PRDP moves.
_RESERVED_OPTIONS = {
    "ksp_type": "ksp_type",
    "pc_type": "pc_type",
    "ksp_max_it": "max_it",
    "ksp_rtol": "rtol",
    "ksp_atol": "atol",
    "ksp_divtol": "divtol",
    "ksp_gmres_restart": "gmres_restart",
}
# Types of the fields a reserved key sets (KSPOptions.from_petsc_options); others are str.
_OPTION_TYPES = {"max_it": int, "rtol": float, "atol": float, "divtol": float, "gmres_restart": int}
# Prefixes of solvers without options_prefix (their options are all their own).
_PRIVATE_PREFIX = "fempdl_"
# Options set under users' prefixes by live solvers: {full name: number of solvers}.
_ADDED_OPTIONS: dict[str, int] = {}
_ADDED_KEYS = "fempdl_added_options"     # the KSP attribute listing the keys it added
# A PETSc options prefix a user can address from the command line.
_PREFIX = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
# Keys that would break the documented semantics outright.
_FORBIDDEN_OPTIONS = {
    "ksp_initial_guess_nonzero": "capped solves always start from a zero initial guess",
}
ENGINES = ("auto", "petsc", "batched")
ADJOINT_OPERATORS = ("auto", "transpose", "assembled")
# Preconditioners whose transpose is missing or wrong (scripts/bench_pc_transpose.py):
# PETSc 3.18's fieldsplit transpose falls back silently (error 0.56 on the DFG
# channel) and its hypre one returns a wrong answer; 3.25 transposes a Schur
# fieldsplit but not LSC inside it (an error), and neither has one for SOR.
_NO_TRUE_TRANSPOSE = frozenset({"fieldsplit", "hypre", "sor"})
# The B B^T solve inside the "schur" preset's LSC: hypre's BoomerAMG where the
# PETSc build has hypre (Debian's), else MUMPS LU with null-pivot detection
# (PyPI's PETSc has no hypre; GAMG there breaks down, PETSc's LU fails on the
# singular B B^T of an enclosed flow). On Debian's PETSc both give the same
# iteration counts to within 2 on the Oseen benchmarks.
_LSC_INNER = ({"fieldsplit_p_lsc_pc_type": "hypre"} if PETSc.Sys.hasExternalPackage("hypre") else
              {"fieldsplit_p_lsc_pc_type": "lu", "fieldsplit_p_lsc_pc_factor_mat_solver_type": "mumps",
               "fieldsplit_p_lsc_mat_mumps_icntl_24": 1})
# The "amg" preset's preconditioner: hypre's BoomerAMG where PETSc has hypre (its
# transpose is wrong in 3.18, so the adjoint solves the assembled A^T), else GAMG.
_AMG = (dict(pc_type="hypre", petsc_options={"pc_hypre_type": "boomeramg"})
        if PETSc.Sys.hasExternalPackage("hypre") else dict(pc_type="gamg"))
DEFAULT_RTOL = 1e-10
DEFAULT_CAP = 20  # max_it when not given, for iterative methods (direct ones get None)
_UNSET = object()  # max_it not given
DEFAULT_CONVERGED_MAX_IT = 10_000


class SolverFailedError(RuntimeError):
    """A solve ended in anything other than convergence or reaching its cap.

    Attributes:
        stats: the :class:`SolveStats` of the failed solve.
    """

    def __init__(self, message: str, stats: "SolveStats"):
        super().__init__(message)
        self.stats = stats


@dataclass(frozen=True)
class KSPOptions:
    """Immutable, validated options of a (possibly capped) PETSc linear solve.

    Args:
        ksp_type: any PETSc KSP type name (``"richardson"``, ``"cg"``, ``"gmres"``,
            ``"preonly"``, ...).
        pc_type: any PETSc PC type name (``"jacobi"``, ``"none"``, ``"lu"``, ...).
        max_it: the iteration cap K (int >= 1), or ``None`` to run to ``rtol``.
            Default 20 for iterative methods and ``None`` for direct solves
            (``ksp_type="preonly"``), where a cap has no meaning.
        rtol: relative tolerance. With a cap it applies only if given; without a
            cap it defaults to 1e-10.
        atol: absolute tolerance (default 0 with a cap, PETSc's 1e-50 without).
        divtol: divergence tolerance; ``None`` disables the divergence test
            (a capped iteration is allowed to grow; NaN/inf is still caught).
        gmres_restart: restart length m of GMRES(m) (GMRES-family only).
        petsc_options: further PETSc options without the leading ``-`` and
            without a prefix, e.g. ``{"ksp_gmres_modifiedgramschmidt": None}`` or
            ``{"ksp_richardson_scale": 0.8}``; applied under a private prefix and
            removed from the global database when the solver is destroyed. PETSc does not
            report unknown names here: a misspelled option is ignored. Note
            that Dirichlet rows are identity rows: a Richardson scale omega != 1
            moves boundary values towards g by a factor (1 - omega) per
            iteration (exact after one iteration only for omega = 1 with Jacobi),
            and diverges for omega outside (0, 2) with nonzero boundary data.
        adjoint: options of the transposed (adjoint) solve. ``None`` means the
            same solver with the same cap (PRDP moves both together); given
            options decouple the adjoint, including its cap.
        on_failure: ``"raise"`` (default) raises :class:`SolverFailedError` when a
            solve diverges, breaks down or produces NaN/inf; ``"warn"`` returns
            the iterate with a warning (never NaN without a warning).
        engine: who runs the iterations of a layer's batch. ``"petsc"``: one KSP
            solve per sample (any KSP/PC, MPI). ``"batched"``: all samples at
            once, one sparse-times-dense product per iteration
            (:mod:`fempdl.iterative.batched`; capped Richardson, CG or GMRES with Jacobi
            or no preconditioner, serial; used whenever the call's matrix is shared
            by the batch). ``"auto"`` (default): batched where it is faster than
            the PETSc loop (:meth:`BatchedEngine.faster_than_petsc`: Richardson
            from B = 2, CG from B = 8, GMRES never), PETSc otherwise. ``SolveStats.engine`` reports which ran.
        adjoint_operator: how the transposed solve gets A^T. ``"transpose"``:
            KSPSolveTranspose on A (the preconditioner's transpose is applied).
            ``"assembled"``: an explicitly assembled A^T (PETSc's MatTranspose,
            refreshed whenever A changes) solved by a normal KSPSolve with the
            adjoint options. ``"auto"`` (default): assembled for preconditioners
            whose transpose PETSc lacks or gets wrong (fieldsplit: 3.18 has no
            transpose and KSPSolveTranspose silently falls back, 3.25 has none
            for the LSC Schur preconditioner; hypre: wrong in 3.18; SOR: none),
            transpose otherwise.
        lag_preconditioner: when a call solves several samples with different
            matrices, set the preconditioner up on the first sample's matrix and
            reuse it for the others (forward and adjoint). Set-up (e.g. the LU of
            a fieldsplit's velocity block) then costs once per call instead of
            once per sample; the Krylov method still runs on each sample's own
            matrix, and a capped solve still runs exactly ``max_it`` iterations,
            but a converged one may need more of them.
        options_prefix: a PETSc options prefix of your own, e.g. ``"myprefix_"``:
            the layer's KSP reads the options database under it when it is
            created, so command-line options such as ``-myprefix_ksp_monitor``,
            ``-myprefix_ksp_view`` or ``-myprefix_ksp_converged_reason`` reach it
            (a separate adjoint KSP reads ``myprefix_adj_``). Options given there
            override these fields (a ``-myprefix_ksp_max_it`` fights the cap
            PRDP moves: leave the cap to ``max_it``); a key given both there and
            in ``petsc_options`` keeps the database's value. Only the keys this
            solver added are removed when it is destroyed. The batched engine
            reads no PETSc options, so a prefix makes ``engine="auto"`` use
            PETSc. petsc4py reads ``sys.argv`` only when the script calls
            ``petsc4py.init(sys.argv)`` before importing fempdl; the environment
            variable ``PETSC_OPTIONS`` works always. A pure cap computes no
            residual norm (a monitor prints 0); give
            ``petsc_options={"ksp_norm_type": "unpreconditioned"}`` to see it.
            ``None`` (default): a private prefix per solver.
    """

    ksp_type: str = "richardson"
    pc_type: str = "jacobi"
    max_it: int | None = _UNSET  # type: ignore[assignment]
    rtol: float | None = None
    atol: float | None = None
    divtol: float | None = None
    gmres_restart: int | None = None
    petsc_options: Mapping[str, Any] = field(default_factory=dict)
    adjoint: "KSPOptions | None" = None
    on_failure: str = "raise"
    engine: str = "auto"
    adjoint_operator: str = "auto"
    lag_preconditioner: bool = False
    options_prefix: str | None = None

    def __post_init__(self):
        _check_choice("ksp_type", self.ksp_type, _KSP_TYPES)
        _check_choice("pc_type", self.pc_type, _PC_TYPES)
        if self.max_it is _UNSET:
            object.__setattr__(self, "max_it", None if self.ksp_type in _DIRECT_KSP_TYPES else DEFAULT_CAP)
        if self.max_it is not None:
            check_int("max_it", self.max_it, minimum=1, maximum=MAX_PETSC_INT,
                       hint="use max_it=None to run to rtol instead of capping")
            if self.ksp_type in _DIRECT_KSP_TYPES:
                raise ValueError(
                    f"max_it={self.max_it!r} has no effect with ksp_type={self.ksp_type!r} "
                    "(a direct solve); use max_it=None, or an iterative ksp_type to cap it")
        for name in ("rtol", "atol", "divtol"):
            value = getattr(self, name)
            if value is None:
                continue
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise TypeError(f"{name} must be a float or None, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
        if self.rtol is not None and not 0.0 <= self.rtol < 1.0:
            raise ValueError(f"rtol must be in [0, 1), got {self.rtol!r}")
        if self.atol is not None and self.atol < 0.0:
            raise ValueError(f"atol must be >= 0, got {self.atol!r}")
        if self.divtol is not None and self.divtol <= 1.0:
            raise ValueError(f"divtol must be > 1 (a growth factor of the residual), got {self.divtol!r}")
        if self.ksp_type in _DIRECT_KSP_TYPES and self.pc_type not in _FACTORISING_PC_TYPES:
            raise ValueError(
                f"ksp_type={self.ksp_type!r} applies the preconditioner once, which solves the system only "
                f"when it is a factorisation ({sorted(_FACTORISING_PC_TYPES)}); with pc_type={self.pc_type!r} "
                "the result is not the solution. Use pc_type='lu' (KSPOptions.preset('lu')) for a direct "
                "solve, or an iterative ksp_type such as 'richardson' (max_it=1 applies the preconditioner once)")
        if self.gmres_restart is not None:
            check_int("gmres_restart", self.gmres_restart, minimum=1, maximum=MAX_PETSC_INT)
            if self.ksp_type not in _RESTARTED_KSP_TYPES:
                raise ValueError(
                    f"gmres_restart is only meaningful for {sorted(_RESTARTED_KSP_TYPES)}, "
                    f"got ksp_type={self.ksp_type!r}; drop gmres_restart or change ksp_type")
        object.__setattr__(self, "petsc_options", _frozen_petsc_options(self.petsc_options))
        if self.adjoint is not None:
            if not isinstance(self.adjoint, KSPOptions):
                raise TypeError(f"adjoint must be KSPOptions or None, got {type(self.adjoint).__name__}")
            if self.adjoint.adjoint is not None:
                raise ValueError("adjoint options must not have an adjoint of their own")
        if self.on_failure not in ("raise", "warn"):
            raise ValueError(f"on_failure must be 'raise' or 'warn', got {self.on_failure!r}")
        if self.engine not in ENGINES:
            raise ValueError(f"engine must be one of {list(ENGINES)}, got {self.engine!r}")
        if not isinstance(self.lag_preconditioner, bool):
            raise TypeError(f"lag_preconditioner must be True or False, got {self.lag_preconditioner!r}")
        if self.adjoint_operator not in ADJOINT_OPERATORS:
            raise ValueError(f"adjoint_operator must be one of {list(ADJOINT_OPERATORS)}, "
                             f"got {self.adjoint_operator!r}")
        if self.options_prefix is not None and (not isinstance(self.options_prefix, str)
                                                or not _PREFIX.fullmatch(self.options_prefix)
                                                or self.options_prefix.startswith(_PRIVATE_PREFIX)):
            raise ValueError(f"options_prefix must be letters, digits and underscores starting with a letter, "
                             f"not starting with {_PRIVATE_PREFIX!r} (fempdl's own), e.g. 'myprefix_' (no "
                             f"leading '-'); got {self.options_prefix!r}")

    def __hash__(self):
        # petsc_options is a read-only mapping: hash its items.
        return hash(tuple((f.name, tuple(sorted(v.items())) if f.name == "petsc_options" else v)
                          for f in dataclasses.fields(self) for v in (getattr(self, f.name),)))

    @classmethod
    def from_petsc_options(cls, options: Mapping[str, Any], **fields) -> "KSPOptions":
        """Options from a DOLFINx-style PETSc options dict, as given to
        ``dolfinx.fem.petsc.LinearProblem(..., petsc_options=...)``.

        ``ksp_type``, ``pc_type``, ``ksp_rtol``, ``ksp_atol``, ``ksp_max_it``,
        ``ksp_divtol`` and ``ksp_gmres_restart`` become the fields of the same
        meaning (numbers may be given as strings, as on a command line); every
        other key goes into ``petsc_options``. Without ``ksp_max_it`` the solve
        runs to ``ksp_rtol`` (default 1e-10) and not reaching it is an error,
        as PETSc would report; with it the solve is capped there. Keyword
        arguments set any other field (``options_prefix=``, ``adjoint=``, ...).
        Missing types default to PETSc's: GMRES with block Jacobi.

        Example:
            ``KSPOptions.from_petsc_options({"ksp_type": "cg", "pc_type": "jacobi", "ksp_rtol": 1e-8})``
        """
        if not isinstance(options, Mapping):
            raise TypeError(f"options must be a mapping of PETSc option name to value, got {type(options).__name__}")
        # PETSc's defaults: GMRES, block Jacobi with ILU(0) blocks (one block, i.e. ILU(0), on one process)
        values = {"ksp_type": "gmres", "pc_type": "bjacobi", "max_it": None}
        rest = {}
        for key, value in options.items():
            name = key[1:] if isinstance(key, str) and key.startswith("-") else key
            if name in _RESERVED_OPTIONS:
                field_name = _RESERVED_OPTIONS[name]
                if field_name in fields:
                    raise ValueError(f"options[{key!r}] and the keyword {field_name}= both set {field_name}; "
                                     "give one of them")
                values[field_name] = _parse_option(key, value, _OPTION_TYPES.get(field_name, str))
            else:
                rest[name] = value
        if "petsc_options" in fields:
            rest = {**rest, **fields.pop("petsc_options")}
        return cls(**{**values, **fields}, petsc_options=rest)

    @classmethod
    def preset(cls, name: str, **overrides) -> "KSPOptions":
        """Options from a named preset, with any field overridden.

        Presets: ``"jacobi"`` (Richardson + PCJACOBI, the PRDP paper's solver),
        ``"cg"`` (CG + Jacobi), ``"gmres"`` (GMRES(30) + Jacobi),
        ``"gmres-ilu"`` (GMRES(30) + ILU(0): non-symmetric systems without a
        saddle point, e.g. a Burgers step), ``"amg"`` (CG + algebraic multigrid:
        hypre BoomerAMG, or PETSc's GAMG where PETSc has no hypre; symmetric
        positive problems on large meshes, where Jacobi's iteration count grows
        with the mesh), ``"schur"`` (GMRES(50) with a
        full Schur-complement fieldsplit: velocity block by LU, Schur complement
        by the least-squares commutator (PCLSC, its B B^T solve by hypre
        BoomerAMG, or by MUMPS where PETSc has no hypre); for saddle-point problems with fields ``"u"`` and ``"p"``,
        the Stokes and Oseen forms, whose iteration counts stay flat down to
        small viscosities where "selfp" does not: scripts/bench_flow.py),
        ``"lu"`` (direct; MUMPS, which pivots through
        the zero pressure block of a saddle point). Iterative presets run to
        rtol=1e-10 unless ``max_it`` caps them.

        Example:
            ``KSPOptions.preset("jacobi", max_it=20)``
        """
        if name not in PRESETS:
            raise ValueError(f"unknown preset {name!r}; choose one of {sorted(PRESETS)}")
        return dataclasses.replace(PRESETS[name], **overrides)

    @property
    def capped(self) -> bool:
        """True when the solve stops at ``max_it`` rather than at a tolerance."""
        return self.max_it is not None

    @property
    def direct(self) -> bool:
        return self.ksp_type in _DIRECT_KSP_TYPES

    @property
    def assembled_adjoint(self) -> bool:
        """Whether transposed solves run on an explicitly assembled A^T."""
        if self.adjoint_operator == "auto":
            return self.adjoint_options.pc_type in _NO_TRUE_TRANSPOSE
        return self.adjoint_operator == "assembled"

    @property
    def adjoint_options(self) -> "KSPOptions":
        """The options of the transposed solve (the forward ones by default)."""
        return self if self.adjoint is None else self.adjoint

    def with_max_it(self, max_it: int | None) -> "KSPOptions":
        """A copy with a new cap (the adjoint override, if any, keeps its own)."""
        return dataclasses.replace(self, max_it=max_it)

    def petsc_tolerances(self) -> dict:
        """The (rtol, atol, divtol, max_it) that realise these semantics in PETSc."""
        if self.capped:
            rtol = 0.0 if self.rtol is None else self.rtol
            atol = 0.0 if self.atol is None else self.atol
            max_it = self.max_it
        else:
            rtol = DEFAULT_RTOL if self.rtol is None else self.rtol
            atol = 1e-50 if self.atol is None else self.atol
            max_it = DEFAULT_CONVERGED_MAX_IT
        divtol = 1e300 if self.divtol is None else self.divtol
        return {"rtol": rtol, "atol": atol, "divtol": divtol, "max_it": max_it}

    def skips_residual_norm(self) -> bool:
        """Whether a solve may run with NORM_NONE (pure cap, no tolerance asked)."""
        return (self.capped and self.rtol is None and self.atol is None and self.divtol is None
                and self.ksp_type in _NORM_FREE_KSP_TYPES and "ksp_norm_type" not in self.petsc_options)




@dataclass(frozen=True)
class SolveStats:
    """What one linear solve did.

    Attributes:
        iterations: Krylov iterations run (1 for a direct solve).
        reason: PETSc's converged reason (> 0 converged, < 0 diverged/stopped).
        reason_name: its name, e.g. ``"DIVERGED_MAX_IT"`` (= the cap was reached).
        residual_norm: final residual norm, or ``None`` when not computed (NORM_NONE).
        time: wall time of the iterations in seconds (the KSP solve after its set-up).
        capped: True when the solve stopped because it reached ``max_it``.
        ok: False when the solve diverged, broke down or produced NaN/inf.
        engine: ``"petsc"`` (a KSP solve) or ``"batched"`` (one column of a
            batched iteration; ``time`` is its share of the batch).
        setup_time: seconds in KSPSetUp before the iterations (the
            preconditioner's set-up or factorisation; about 0 while A is unchanged).
    """

    iterations: int
    reason: int
    reason_name: str
    residual_norm: float | None
    time: float
    capped: bool
    ok: bool
    engine: str = "petsc"
    setup_time: float = 0.0


@dataclass
class CumulativeStats:
    """Cumulative iteration and time counters of a layer (summed over samples).

    ``forward_iterations + backward_iterations`` is the cost metric PRDP savings
    are quoted in. Seconds, split by what they bought: ``solve_time`` the
    iterations (forward + backward), ``setup_time`` preconditioner set-up and
    factorisations, ``assembly_time`` matrices, right-hand sides and gradient
    forms, ``adjoint_operator_time`` forming an explicit A^T; ``layer_time`` is
    the whole forward and backward of the layer (those and the conversions).
    """

    forward_iterations: int = 0
    backward_iterations: int = 0
    forward_solves: int = 0
    backward_solves: int = 0
    forward_time: float = 0.0
    backward_time: float = 0.0
    layer_time: float = 0.0
    setup_time: float = 0.0
    assembly_time: float = 0.0
    adjoint_operator_time: float = 0.0
    max_forward_iterations: int = 0
    failures: int = 0
    solves_by_engine: dict = field(default_factory=dict)
    last: SolveStats | None = None

    def record(self, direction: str, stats: SolveStats) -> None:
        """Add one solve; ``direction`` is ``"forward"`` or ``"backward"``."""
        if direction == "forward":
            self.max_forward_iterations = max(self.max_forward_iterations, stats.iterations)
            self.forward_iterations += stats.iterations
            self.forward_solves += 1
            self.forward_time += stats.time
        elif direction == "backward":
            self.backward_iterations += stats.iterations
            self.backward_solves += 1
            self.backward_time += stats.time
        else:
            raise ValueError(f"direction must be 'forward' or 'backward', got {direction!r}")
        self.setup_time += stats.setup_time
        self.failures += not stats.ok
        self.solves_by_engine[stats.engine] = self.solves_by_engine.get(stats.engine, 0) + 1
        self.last = stats

    @property
    def total_iterations(self) -> int:
        return self.forward_iterations + self.backward_iterations

    @property
    def solve_time(self) -> float:
        return self.forward_time + self.backward_time

    def reset(self) -> None:
        fresh = CumulativeStats()
        for f in dataclasses.fields(self):
            setattr(self, f.name, getattr(fresh, f.name))


class CappedSolver:
    """A PETSc KSP on one operator, with a forward and a transposed solve.

    Follows the init / compute / transpose split: build once for an operator,
    call :meth:`solve` and :meth:`solve_transpose` many times. When the operator's
    entries are reassembled in place, PETSc notices and rebuilds the
    preconditioner on the next solve.

    Args:
        A: the assembled operator (square PETSc Mat).
        options: the solver options.
        prefix: options prefix; ``options.options_prefix`` when set, else a
            unique private one.

    Attributes:
        stats: :class:`CumulativeStats` of every solve (``solve`` counts as
            forward, ``solve_transpose`` as backward), failed ones included.

    The KSP objects are destroyed by :meth:`destroy` (or on leaving a ``with``
    block); PETSc objects are not left to the garbage collector.
    """

    _counter = itertools.count()

    def __init__(self, A: PETSc.Mat, options: KSPOptions, *, prefix: str | None = None,
                 fields: Mapping[str, np.ndarray] | None = None):
        if not isinstance(options, KSPOptions):
            raise TypeError(f"options must be KSPOptions, got {type(options).__name__}")
        self._options = options
        self._A = A
        self._fields = fields
        self._prefix = prefix or options.options_prefix or f"fempdl_ksp{next(self._counter)}_"
        self._ksp = _create_ksp(A, options, self._prefix, fields)
        # The adjoint has its own KSP when its options differ, or when it runs on
        # an assembled A^T (created at the first transposed solve: A must be assembled).
        self._ksp_adjoint = None
        self._At = None
        self._At_state = None
        if options.adjoint is not None and not options.assembled_adjoint:
            self._ksp_adjoint = _create_ksp(A, options.adjoint, self._prefix + "adj_", fields)
        self.stats = CumulativeStats()
        self.reuse_preconditioner = False

    @property
    def reuse_preconditioner(self) -> bool:
        """While True, solves keep the preconditioners set up for earlier matrices
        (``KSPOptions.lag_preconditioner``: the system sets it between samples)."""
        return self._reuse

    @reuse_preconditioner.setter
    def reuse_preconditioner(self, value: bool) -> None:
        self._reuse = bool(value)

    @property
    def options(self) -> KSPOptions:
        return self._options

    @property
    def max_it(self) -> int | None:
        return self._options.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        """Move the cap of the forward solve (and of a coupled adjoint)."""
        new = self._options.with_max_it(value)  # validates
        # A coupled adjoint on its own KSP (the one on an assembled A^T) moves with the forward cap.
        coupled = [self._ksp] + ([self._ksp_adjoint] if new.adjoint is None and self._ksp_adjoint else [])
        for ksp in coupled:
            if new.skips_residual_norm() != self._options.skips_residual_norm():
                _set_norm_type(ksp, new)
            ksp.setTolerances(**new.petsc_tolerances())
        self._options = new

    @property
    def ksp(self) -> PETSc.KSP:
        """The forward KSP (for inspection; do not change its tolerances)."""
        return self._ksp

    def solve(self, b: PETSc.Vec, x: PETSc.Vec, *, warm: bool = False) -> SolveStats:
        """Solve A x = b; ``x`` is overwritten.

        The iteration starts from zero, or from the values ``x`` holds when
        ``warm`` is True (a warm start: the K iterations then correct that
        guess; direct solves ignore it).

        Raises:
            SolverFailedError: on divergence, breakdown or NaN/inf (unless the
                options say ``on_failure="warn"``). The solve is counted in
                :attr:`stats` either way.
        """
        warm = warm and not self._options.direct   # PCLU under preonly refuses a nonzero guess
        if warm:
            self._ksp.setInitialGuessNonzero(True)
        try:
            return self._run(self._ksp, self._options, b, x, direction="forward")
        finally:
            if warm:
                self._ksp.setInitialGuessNonzero(False)

    def solve_many(self, R: np.ndarray) -> np.ndarray:
        """A X = R for the rows of R (B, n) with one factorisation and one MatMatSolve
        (a direct solve on one process: ``options.direct``); returns X (B, n).

        Each sample is counted as one solve of one iteration, with its share of the time.
        """
        if not self._options.direct or self._A.getComm().getSize() > 1:
            raise ValueError("solve_many needs a direct solve (ksp_type='preonly' with a factorising pc_type) "
                             "on one process")
        batch, n = R.shape
        t0 = time.perf_counter()
        _set_up(self._ksp, self._reuse)
        t1 = time.perf_counter()
        # A dense PETSc matrix is column-major: the rows of R are its columns.
        rhs = PETSc.Mat().createDense((n, batch), array=np.asfortranarray(R.T, dtype=PETSc.ScalarType),
                                      comm=PETSc.COMM_SELF)
        sol = PETSc.Mat().createDense((n, batch), comm=PETSc.COMM_SELF)
        sol.setUp()
        try:
            self._ksp.getPC().getFactorMatrix().matSolve(rhs, sol)
            X = np.array(sol.getDenseArray().T)
        finally:
            rhs.destroy()
            sol.destroy()
        elapsed = time.perf_counter() - t1
        reason = PETSc.KSP.ConvergedReason.CONVERGED_ITS
        for ok in np.isfinite(X).all(axis=1):
            self.record("forward", SolveStats(iterations=1, reason=reason, reason_name=_REASON_NAMES[reason],
                                              residual_norm=None, time=elapsed / batch, capped=False,
                                              ok=bool(ok), setup_time=(t1 - t0) / batch),
                        finite=bool(ok))
        return X

    def solve_transpose(self, b: PETSc.Vec, x: PETSc.Vec) -> SolveStats:
        """Solve A^T x = b with the adjoint options (the forward ones by default),
        by KSPSolveTranspose or on an assembled A^T (``options.assembled_adjoint``)."""
        if self._options.assembled_adjoint:
            return self._run(self._assembled_adjoint_ksp(), self._options.adjoint_options, b, x,
                             direction="backward", transpose=False)
        if self._ksp_adjoint is None:
            return self._run(self._ksp, self._options, b, x, direction="backward")
        return self._run(self._ksp_adjoint, self._options.adjoint, b, x, direction="backward")

    def _assembled_adjoint_ksp(self) -> PETSc.KSP:
        """The KSP on A^T, with A^T refreshed if A changed since it was built."""
        state = self._A.stateGet()
        t0 = time.perf_counter()
        if self._At is None:
            # petsc4py's A.transpose() without an argument transposes A in place;
            # an empty Mat as the target asks for a new matrix.
            self._At = PETSc.Mat()
            self._A.transpose(self._At)
            self._ksp_adjoint = _create_ksp(self._At, self._options.adjoint_options, self._prefix + "adj_",
                                            self._fields)
        elif state != self._At_state:
            self._A.transpose(self._At)           # same pattern: reuses A^T's storage
        if state != self._At_state:
            nsp = self._A.getTransposeNullSpace() or self._A.getNullSpace()
            if nsp is not None:
                self._At.setNullSpace(nsp)
            self._At_state = state
        self.stats.adjoint_operator_time += time.perf_counter() - t0
        return self._ksp_adjoint

    def destroy(self) -> None:
        for ksp in (self._ksp, self._ksp_adjoint):
            if ksp is not None:
                _destroy_ksp(ksp)
        if self._At is not None:
            self._At.destroy()
        self._ksp = self._ksp_adjoint = self._At = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.destroy()

    def _run(self, ksp, options: KSPOptions, b, x, *, direction: str, transpose: bool | None = None) -> SolveStats:
        transpose = direction == "backward" if transpose is None else transpose
        operator = ksp.getOperators()[0]
        # A singular operator with an attached null space (e.g. the pressure
        # constant of an enclosed flow): solve for the part of b in the range
        # and return the solution orthogonal to the null space, so the map
        # b -> x is well defined (and its transpose is the adjoint's map).
        nsp = (operator.getTransposeNullSpace() if transpose else None) or operator.getNullSpace()
        if nsp is not None:
            nsp.remove(b)
        b_norm = b.norm()
        self._set_interrupt_checks(ksp, options)
        t0 = time.perf_counter()
        _set_up(ksp, self._reuse)      # the preconditioner's set-up, timed apart from the iterations
        t1 = time.perf_counter()
        try:
            (ksp.solveTranspose if transpose else ksp.solve)(b, x)
        except PETSc.Error as err:
            # petsc4py >= 3.19 wraps an exception raised in a Python monitor
            # (Ctrl-C's KeyboardInterrupt) in a PETSc.Error; 3.18 lets it through.
            if isinstance(err.__cause__, KeyboardInterrupt):
                raise err.__cause__ from None
            raise
        elapsed = time.perf_counter() - t1
        if nsp is not None:
            nsp.remove(x)
        reason = int(ksp.getConvergedReason())
        iterations = int(ksp.getIterationNumber())
        norm_computed = ksp.getNormType() != PETSc.KSP.NormType.NONE
        rnorm = float(ksp.getResidualNorm()) if norm_computed else None
        finite = math.isfinite(x.norm(PETSc.NormType.NORM_INFINITY))
        capped = options.capped and (reason == _DIVERGED_MAX_IT
                                     or (reason == PETSc.KSP.ConvergedReason.CONVERGED_ITS
                                         and iterations >= options.max_it))
        exact = (reason == _DIVERGED_BREAKDOWN and rnorm is not None and rnorm <= _HAPPY_BREAKDOWN * b_norm)
        ok = finite and (reason > 0 or capped or exact)
        stats = SolveStats(iterations=iterations, reason=reason,
                           reason_name=_REASON_NAMES.get(reason, str(reason)),
                           residual_norm=rnorm, time=elapsed, capped=capped, ok=ok, setup_time=t1 - t0)
        return self.record(direction, stats, finite=finite)

    def _set_interrupt_checks(self, ksp: PETSc.KSP, options: KSPOptions) -> None:
        """Give ``ksp`` a monitor that lets a pending KeyboardInterrupt stop a long solve (see
        :data:`INTERRUPT_CHECK_MIN_WORK`), or take it away when the cap has moved below that."""
        cap = DEFAULT_CONVERGED_MAX_IT if options.max_it is None else options.max_it
        wanted = not options.direct and cap * ksp.getOperators()[0].getSize()[0] >= INTERRUPT_CHECK_MIN_WORK
        has = ksp.getAttr("fempdl_interruptible") is not None
        if wanted and not has:
            # Calling into Python runs the pending signal handlers: Ctrl-C raises
            # KeyboardInterrupt inside the monitor, and KSPSolve returns with it.
            ksp.setMonitor(_interrupt_point)
            ksp.setAttr("fempdl_interruptible", True)
        elif has and not wanted:
            ksp.cancelMonitor()
            ksp.setAttr("fempdl_interruptible", None)

    def record(self, direction: str, stats: SolveStats, *, finite: bool = True) -> SolveStats:
        """Count a solve (also one run outside this KSP, e.g. by the batched
        engine) and raise or warn per the options if it failed."""
        self.stats.record(direction, stats)
        if not stats.ok:
            self.report_failure(direction, stats, finite=finite)
        return stats

    def report_failure(self, direction: str, stats: SolveStats, *, finite: bool, samples: int = 1) -> None:
        """Raise :class:`SolverFailedError` or warn (per ``on_failure``) for a failed solve."""
        options = self._options if direction == "forward" else self._options.adjoint_options
        _report_failure(options, stats, finite, direction == "backward", samples)


def _interrupt_point(ksp, iteration, residual_norm) -> None:
    """A KSP monitor that does nothing: being Python, it lets signal handlers run (module docstring)."""


def petsc_to_scipy(A: PETSc.Mat) -> "scipy.sparse.csr_matrix":
    """The local rows of an assembled PETSc AIJ matrix as a scipy CSR matrix (a copy)."""
    import scipy.sparse as sp

    indptr, indices, data = A.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=(A.getLocalSize()[0], A.getSize()[1]))


def capped_solve_stats(options: KSPOptions, seconds: float, finite: bool, engine: str) -> SolveStats:
    """Stats of a pure-cap solve that ran ``options.max_it`` iterations outside PETSc."""
    reason = PETSc.KSP.ConvergedReason.CONVERGED_ITS
    return SolveStats(iterations=options.max_it, reason=reason, reason_name=_REASON_NAMES[reason],
                      residual_norm=None, time=seconds, capped=True, ok=finite, engine=engine)


class SolverWarning(RuntimeWarning):
    """A solve failed and ``on_failure="warn"`` asked for the iterate anyway."""


def _report_failure(options: KSPOptions, stats: SolveStats, finite: bool, transpose: bool,
                    samples: int = 1) -> None:
    what = "transposed solve" if transpose else "solve"
    if samples > 1:
        what += f" of {samples} samples"
    if not finite:
        cause = "produced NaN or inf"
        if options.direct:
            fix = ("check for a zero coefficient (e.g. kappa = 0) or a missing Dirichlet condition: "
                   "the matrix is probably singular")
        else:
            fix = ("check the inputs and the operator (e.g. a zero or negative coefficient, or an "
                   "unstable damping), or use a more robust solver such as KSPOptions.preset('lu')")
    elif stats.reason == _DIVERGED_MAX_IT:
        cause = f"did not reach rtol={options.petsc_tolerances()['rtol']:g} in {stats.iterations} iterations"
        fix = "try a stronger pc_type or ksp_type, a larger rtol, or cap the solve on purpose with max_it=K"
    else:
        cause = f"stopped with {stats.reason_name} after {stats.iterations} iterations"
        fix = ("the operator may be singular or indefinite for this method; try ksp_type='gmres', "
               "KSPOptions.preset('lu'), or a larger divtol")
    message = (f"{options.ksp_type}+{options.pc_type} {what} {cause}"
               + (f" (residual norm {stats.residual_norm:.3e})" if stats.residual_norm is not None else "")
               + f"; {fix}. Pass on_failure='warn' to get the iterate with a warning instead.")
    if options.on_failure == "warn":
        warn_at_caller(message, SolverWarning)
    else:
        raise SolverFailedError(message, stats)


def warn_at_caller(message: str, category: type[Warning]) -> None:
    """Warn with the location of the first frame outside fempdl and torch, so the
    warning points at the user's line (the call stack runs through autograd)."""
    frame, level = sys._getframe(1), 1
    while frame is not None and frame.f_globals.get("__name__", "").split(".")[0] in ("fempdl", "torch"):
        frame, level = frame.f_back, level + 1
    warnings.warn(message, category, stacklevel=level + 1)


def _create_ksp(A: PETSc.Mat, options: KSPOptions, prefix: str, fields=None) -> PETSc.KSP:
    ksp = PETSc.KSP().create(A.getComm())
    ksp.setOptionsPrefix(prefix)
    ksp.setOperators(A)
    ksp.setType(options.ksp_type)
    ksp.getPC().setType(options.pc_type)
    if options.pc_type == "fieldsplit":
        if not fields:
            raise ValueError("pc_type='fieldsplit' needs the problem's fields (e.g. the velocity and pressure "
                             "DOFs of a Stokes or Oseen problem); this problem has none")
        start = A.getOwnershipRange()[0]
        ksp.getPC().setFieldSplitIS(*[(name, PETSc.IS().createGeneral(
            (start + np.sort(dofs)).astype(PETSc.IntType), comm=A.getComm())) for name, dofs in fields.items()])
    if options.gmres_restart is not None:
        ksp.setGMRESRestart(options.gmres_restart)
    if options.pc_type in ("lu", "cholesky") and A.getComm().getSize() > 1 \
            and "pc_factor_mat_solver_type" not in options.petsc_options:
        # PETSc's own LU is serial only.
        ksp.getPC().setFactorSolverType("mumps")
    _set_norm_type(ksp, options)
    ksp.setTolerances(**options.petsc_tolerances())
    ksp.setInitialGuessNonzero(False)
    petsc_options = dict(options.petsc_options)
    if options.pc_type in ("lu", "cholesky") and A.getNullSpace() is not None and (
            petsc_options.get("pc_factor_mat_solver_type") == "mumps" or A.getComm().getSize() > 1):
        # A singular operator (an enclosed flow's pressure constant): without null-pivot
        # detection MUMPS factorises it as if regular and returns a wrong solution.
        petsc_options.setdefault("mat_mumps_icntl_24", 1)
    db = PETSc.Options()
    if prefix.startswith(_PRIVATE_PREFIX):
        for key, value in petsc_options.items():
            db[prefix + key] = "" if value is None else value
        ksp.setAttr(_ADDED_KEYS, None)           # destroy removes everything under the prefix
    else:
        # A user's prefix: options already in the database (the command line's, or
        # another solver's under the same prefix) win and are not this solver's to remove.
        added = []
        for key, value in petsc_options.items():
            name = prefix + key
            if name in _ADDED_OPTIONS:
                _ADDED_OPTIONS[name] += 1
            elif not db.hasName(name):
                db[name] = "" if value is None else value
                _ADDED_OPTIONS[name] = 1
            else:
                continue
            added.append(name)
        ksp.setAttr(_ADDED_KEYS, added)
    # Inner solvers (fieldsplit blocks) read their options when the
    # preconditioner is first set up, so the options stay until _destroy_ksp.
    try:
        ksp.setFromOptions()
    except PETSc.Error as err:
        _destroy_ksp(ksp)
        raise _rejected_option(A, options, err) from None
    return ksp


def _rejected_option(A: PETSc.Mat, options: KSPOptions, err: PETSc.Error) -> ValueError:
    """The error for petsc_options PETSc refused, naming the option (found by trying each alone)."""
    for key, value in options.petsc_options.items():
        probe = PETSc.KSP().create(A.getComm())
        prefix = f"fempdl_probe{next(CappedSolver._counter)}_"
        probe.setOptionsPrefix(prefix)
        probe.setOperators(A)
        probe.setType(options.ksp_type)
        probe.getPC().setType(options.pc_type)
        PETSc.Options()[prefix + key] = "" if value is None else value
        try:
            probe.setFromOptions()
        except PETSc.Error:
            return ValueError(f"petsc_options[{key!r}] = {value!r} was rejected by PETSc for ksp_type="
                              f"{options.ksp_type!r}, pc_type={options.pc_type!r} (PETSc error code {err.ierr}); "
                              "give the value the option takes (a number for scales and tolerances, an int for "
                              "counts, a type name for types)")
        finally:
            _destroy_ksp(probe)
    return ValueError(f"PETSc rejected petsc_options {dict(options.petsc_options)} for ksp_type="
                      f"{options.ksp_type!r}, pc_type={options.pc_type!r} (PETSc error code {err.ierr}); check "
                      "each option's value")


def _set_up(ksp: PETSc.KSP, reuse: bool) -> None:
    """KSPSetUp, and the set-up of a fieldsplit's inner solvers (otherwise done lazily
    in the first iteration); with ``reuse`` the preconditioner is kept as it is."""
    pc = ksp.getPC()
    pc.setReusePreconditioner(reuse)
    ksp.setUp()
    pc.setUp()     # KSPSetUp leaves a changed matrix's preconditioner to the solve
    if not reuse and pc.getType() == "fieldsplit":
        # The blocks' preconditioners (e.g. the velocity block's LU) refresh in the first
        # iteration otherwise: their KSPs see the same submatrix objects, new values.
        for sub in pc.getFieldSplitSubKSP():
            sub.getPC().setUp()


def _destroy_ksp(ksp: PETSc.KSP) -> None:
    """Destroy ``ksp`` and remove its options from the global database: everything
    under a private prefix; under a user's prefix only the keys it added (once no
    other solver under that prefix uses them)."""
    db = PETSc.Options()
    added = ksp.getAttr(_ADDED_KEYS)
    if added is None:
        prefix = ksp.getOptionsPrefix() or ""
        for key in db.getAll():
            if prefix and key.startswith(prefix):
                db.delValue(key)
    else:
        for name in added:
            _ADDED_OPTIONS[name] -= 1
            if not _ADDED_OPTIONS[name]:
                del _ADDED_OPTIONS[name]
                db.delValue(name)
    ksp.destroy()


def _set_norm_type(ksp: PETSc.KSP, options: KSPOptions) -> None:
    if options.skips_residual_norm():
        ksp.setNormType(PETSc.KSP.NormType.NONE)
    elif options.ksp_type in _NORM_FREE_KSP_TYPES and "ksp_norm_type" not in options.petsc_options:
        ksp.setNormType(PETSc.KSP.NormType.PRECONDITIONED if options.ksp_type != "richardson"
                        else PETSc.KSP.NormType.UNPRECONDITIONED)


def _frozen_petsc_options(options) -> Mapping[str, Any]:
    if not isinstance(options, Mapping):
        raise TypeError(f"petsc_options must be a mapping of option name to value, got {type(options).__name__}")
    clean = {}
    for key, value in options.items():
        if not isinstance(key, str) or not key or key.startswith("-"):
            raise ValueError(f"petsc_options keys are option names without the leading '-', got {key!r}")
        if key in _FORBIDDEN_OPTIONS:
            raise ValueError(f"petsc_options[{key!r}] is not supported: {_FORBIDDEN_OPTIONS[key]}")
        if key in _RESERVED_OPTIONS:
            raise ValueError(f"petsc_options[{key!r}] conflicts with a KSPOptions field; "
                             f"set {_RESERVED_OPTIONS[key]} instead, or build the options from a DOLFINx-style "
                             "dict with KSPOptions.from_petsc_options")
        if value is not None and not isinstance(value, (str, bool, int, float, np.integer, np.floating)):
            raise TypeError(f"petsc_options[{key!r}] must be str, number, bool or None, got {value!r}")
        clean[key] = value
    return types.MappingProxyType(clean)


def _parse_option(key: str, value, kind: type):
    """A reserved option's value as its field's type (strings parsed, as from a command line)."""
    if kind is str:
        if not isinstance(value, str):
            raise TypeError(f"options[{key!r}] must be a type name (str), got {value!r}")
        return value
    if isinstance(value, bool) or value is None:
        raise TypeError(f"options[{key!r}] must be a number, got {value!r}")
    try:
        number = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"options[{key!r}] must be a number, got {value!r}") from None
    if kind is int:
        if not number.is_integer():
            raise ValueError(f"options[{key!r}] must be a whole number, got {value!r}")
        return int(number)
    return number


def _check_choice(name: str, value, allowed: frozenset) -> None:
    if not isinstance(value, str):
        raise TypeError(f"{name} must be a str, got {value!r}")
    if value not in allowed:
        raise ValueError(f"{name}={value!r} is not a PETSc type; choose one of {sorted(allowed)}")


def check_int(name: str, value, *, minimum: int, maximum: int | None = None, hint: str = "") -> None:
    """Raise TypeError unless ``value`` is an int (numpy ints too, bools not), ValueError outside [minimum, maximum]."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise TypeError(f"{name} must be an int, got {value!r}" + (f"; {hint}" if hint else ""))
    if value < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {value!r}" + (f"; {hint}" if hint else ""))
    if maximum is not None and value > maximum:
        raise ValueError(f"{name} must be <= {maximum} (the largest PETSc int of this build), got {value!r}")


PRESETS: Mapping[str, KSPOptions] = types.MappingProxyType({
    "jacobi": KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=None),
    "cg": KSPOptions(ksp_type="cg", pc_type="jacobi", max_it=None),
    "gmres": KSPOptions(ksp_type="gmres", pc_type="jacobi", gmres_restart=30, max_it=None),
    "gmres-ilu": KSPOptions(ksp_type="gmres", pc_type="ilu", gmres_restart=30, max_it=None),
    "schur": KSPOptions(ksp_type="gmres", pc_type="fieldsplit", gmres_restart=50, max_it=None, petsc_options={
        "pc_fieldsplit_type": "schur", "pc_fieldsplit_schur_fact_type": "full",
        "pc_fieldsplit_schur_precondition": "self",
        "fieldsplit_u_ksp_type": "preonly", "fieldsplit_u_pc_type": "lu",
        "fieldsplit_p_ksp_type": "preonly", "fieldsplit_p_pc_type": "lsc",
        **_LSC_INNER}),
    "amg": KSPOptions(ksp_type="cg", max_it=None, **_AMG),
    "lu": KSPOptions(ksp_type="preonly", pc_type="lu", max_it=None,
                     petsc_options={"pc_factor_mat_solver_type": "mumps"}),
})
