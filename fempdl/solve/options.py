"""KSPOptions: an immutable, validated description of a (possibly capped) PETSc linear solve, and its presets.

Semantics of a capped solve (``max_it`` set): it starts from a zero initial
guess (or from a given one: a warm start) and runs exactly ``max_it`` iterations, never more. It stops earlier only
if the user asked for a tolerance (``rtol``/``atol``) and it is met, or if the
residual vanishes exactly. Without ``rtol`` the convergence test is effectively
disabled (rtol = atol = 0, no divergence test), and Richardson/CG/Chebyshev skip
computing the residual norm altogether (PETSc's NORM_NONE), which is 15-25%
faster; ``SolveStats.residual_norm`` is then ``None``.

With ``max_it=None`` a solve runs to ``rtol`` (default 1e-10) and not reaching it
is a failure. Presets (:data:`PRESETS`, :meth:`KSPOptions.preset`): ``"jacobi"``
(Richardson + PCJACOBI), ``"cg"``, ``"gmres"``, ``"gmres-ilu"``, ``"schur"``, ``"amg"``, ``"lu"``,
``"cholesky"``.
"""
from __future__ import annotations

import dataclasses
import math
import re
import types
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from petsc4py import PETSc

from fempdl.core.checks import check_int, is_real, python_number
from fempdl.solve.option_checks import (
    FACTORISING_PC_TYPES,
    OPTION_TYPES,
    RESERVED_OPTIONS,
    check_choice,
    factorises,
    frozen_petsc_options,
    inner_pc,
    parse_option,
)

__all__ = ["KSPOptions", "PRESETS", "ENGINES", "ADJOINT_OPERATORS", "MAX_PETSC_INT", "DEFAULT_RTOL",
           "DEFAULT_CONVERGED_MAX_IT", "PRIVATE_PREFIX", "NORM_FREE_KSP_TYPES", "STATIONARY_KSP_TYPES"]

_KSP_TYPES = frozenset(getattr(PETSc.KSP.Type, n) for n in dir(PETSc.KSP.Type) if n.isupper())
_PC_TYPES = frozenset(getattr(PETSc.PC.Type, n) for n in dir(PETSc.PC.Type) if n.isupper())
_RESTARTED_KSP_TYPES = frozenset({"gmres", "fgmres", "lgmres", "dgmres", "pgmres", "pipefgmres"})
# Methods whose iteration does not need the residual norm: with a pure cap they
# run with NORM_NONE (no reduction per iteration).
NORM_FREE_KSP_TYPES = frozenset({"richardson", "cg", "chebyshev"})
_DIRECT_KSP_TYPES = frozenset({"preonly"})
# Stationary iterations: a fixed iteration matrix, which diverges where its spectral radius exceeds 1.
STATIONARY_KSP_TYPES = frozenset({"richardson", "chebyshev"})
# PETSc's largest int in this build (32- or 64-bit indices): larger caps overflow inside PETSc.
MAX_PETSC_INT = int(np.iinfo(PETSc.IntType).max)
PRIVATE_PREFIX = "fempdl_"
# A PETSc options prefix a user can address from the command line.
_PREFIX = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
ENGINES = ("auto", "petsc", "batched")
ADJOINT_OPERATORS = ("auto", "transpose", "assembled")
# Preconditioners whose transpose is missing or wrong (benchmarks/bench_pc_transpose.py):
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
DEFAULT_CONVERGED_MAX_IT = 10_000


@dataclass(frozen=True)
class KSPOptions:
    """Immutable, validated options of a (possibly capped) PETSc linear solve.

    Args:
        ksp_type: any PETSc KSP type name (``"richardson"``, ``"cg"``, ``"gmres"``,
            ``"preonly"``, ...).
        pc_type: any PETSc PC type name (``"jacobi"``, ``"none"``, ``"lu"``, ...).
        max_it: the iteration cap K (int >= 1), or ``None`` (the default) to run
            to ``rtol`` and fail if it is not reached. A cap is only ever what you
            ask for: the same options never mean capped in one place and
            converged in another (a preset is converged unless given ``max_it``).
        rtol: relative tolerance. With a cap it applies only if given; without a
            cap it defaults to 1e-10.
        atol: absolute tolerance (default 0: a solve stops at ``rtol`` relative to its initial residual,
            whatever the data's scale; PETSc's own default, 1e-50, would accept x = 0 for a right-hand
            side below it). Data far from 1 are solved scaled by a power of two
            (:mod:`fempdl.solve.scaling`), a given atol scaled with them.
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
            (:mod:`fempdl.iterative.batched`; Richardson, CG or GMRES with Jacobi
            or no preconditioner, serial, no ``divtol``; Richardson and GMRES with a pure
            cap only, CG also to ``rtol``/``atol`` with or without a cap, each sample
            stopping where its own KSPCG would, with its own iterations and reason in
            the stats; used whenever the call's matrix is shared by the batch).
            ``"auto"`` (default): batched where it measured faster than the PETSc loop
            (:meth:`BatchedEngine.faster_than_petsc`, from the batch size, the method, the cap and
            the matrix's nonzeros: Richardson from B = 8, or from B = 2 once nonzeros x cap reaches
            500k; CG capped or converged from B = 8 on at least 10k nonzeros; GMRES never), PETSc
            otherwise. ``SolveStats.engine`` reports which ran.
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
            but a converged one may need more of them. In a Newton solve's inner
            solve (a Krylov method run to ``rtol``) the factor is kept across Newton
            steps, solves and the adjoint's transposed solves, and set up again on the
            current matrix after a solve that needed more than
            ``core.tuning.LAGGED_REFRESH_ITERATIONS`` iterations: every step still
            solves its own Jacobian to ``rtol`` (the ``"lu-lagged"`` preset).
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
    max_it: int | None = None
    rtol: float | None = None
    atol: float | None = None
    divtol: float | None = None
    gmres_restart: int | None = None
    petsc_options: Mapping[str, Any] = field(default_factory=dict)
    adjoint: KSPOptions | None = None
    on_failure: str = "raise"
    engine: str = "auto"
    adjoint_operator: str = "auto"
    lag_preconditioner: bool = False
    options_prefix: str | None = None

    def __post_init__(self):
        check_choice("ksp_type", self.ksp_type, _KSP_TYPES)
        check_choice("pc_type", self.pc_type, _PC_TYPES)
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
            if not is_real(value):
                raise TypeError(f"{name} must be a float or None, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"{name} must be finite, got {value!r}")
        if self.rtol is not None and not 0.0 <= self.rtol < 1.0:
            raise ValueError(f"rtol must be in [0, 1), got {self.rtol!r}")
        if self.atol is not None and self.atol < 0.0:
            raise ValueError(f"atol must be >= 0, got {self.atol!r}")
        if self.divtol is not None and self.divtol <= 1.0:
            raise ValueError(f"divtol must be > 1 (a growth factor of the residual), got {self.divtol!r}")
        if self.gmres_restart is not None:
            check_int("gmres_restart", self.gmres_restart, minimum=1, maximum=MAX_PETSC_INT)
            if self.ksp_type not in _RESTARTED_KSP_TYPES:
                raise ValueError(
                    f"gmres_restart is only meaningful for {sorted(_RESTARTED_KSP_TYPES)}, "
                    f"got ksp_type={self.ksp_type!r}; drop gmres_restart or change ksp_type")
        # Numpy scalars are stored as python numbers: options are compared, hashed and printed.
        for name in ("max_it", "rtol", "atol", "divtol", "gmres_restart"):
            object.__setattr__(self, name, python_number(getattr(self, name)))
        object.__setattr__(self, "petsc_options", frozen_petsc_options(self.petsc_options))
        if self.ksp_type in _DIRECT_KSP_TYPES and not factorises(self.pc_type, self.petsc_options):
            raise ValueError(
                f"ksp_type={self.ksp_type!r} applies the preconditioner once, which solves the system only "
                f"when it is a factorisation ({sorted(FACTORISING_PC_TYPES)}, or 'redundant' around one); with "
                f"pc_type={self.pc_type!r}{inner_pc(self.petsc_options)} the result is not the solution. Use "
                "pc_type='lu' (KSPOptions.preset('lu')) for a direct solve, or an iterative ksp_type such as "
                "'richardson' (max_it=1 applies the preconditioner once)")
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
                                                or self.options_prefix.startswith(PRIVATE_PREFIX)):
            raise ValueError(f"options_prefix must be letters, digits and underscores starting with a letter, "
                             f"not starting with {PRIVATE_PREFIX!r} (fempdl's own), e.g. 'myprefix_' (no "
                             f"leading '-'); got {self.options_prefix!r}")

    def __hash__(self):
        # petsc_options is a read-only mapping: hash its items.
        return hash(tuple((f.name, tuple(sorted(v.items())) if f.name == "petsc_options" else v)
                          for f in dataclasses.fields(self) for v in (getattr(self, f.name),)))

    @classmethod
    def from_petsc_options(cls, options: Mapping[str, Any], **fields) -> KSPOptions:
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
        rest, given = {}, {}
        for key, value in options.items():
            name = key[1:] if isinstance(key, str) and key.startswith("-") else key
            if isinstance(name, str) and name.lower() in RESERVED_OPTIONS:
                field_name = RESERVED_OPTIONS[name.lower()]   # PETSc reads option names case-insensitively
                if field_name in fields:
                    raise ValueError(f"options[{key!r}] and the keyword {field_name}= both set {field_name}; "
                                     "give one of them")
                if field_name in given:
                    raise ValueError(f"options[{given[field_name]!r}] and options[{key!r}] both set {field_name} "
                                     "(PETSc ignores the letter case of option names); give one of them")
                given[field_name] = key
                values[field_name] = parse_option(key, value, OPTION_TYPES.get(field_name, str))
            else:
                rest[name] = value
        if "petsc_options" in fields:
            rest = {**rest, **fields.pop("petsc_options")}
        return cls(**{**values, **fields}, petsc_options=rest)

    @classmethod
    def preset(cls, name: str, **overrides) -> KSPOptions:
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
        small viscosities where "selfp" does not: benchmarks/bench_flow.py),
        ``"lu"`` (direct; MUMPS, which pivots through
        the zero pressure block of a saddle point), ``"cholesky"`` (direct, for
        problems declared symmetric: PETSc's own Cholesky on one process, about
        half the work of LU and without MUMPS's set-up cost on small systems;
        MUMPS under MPI), ``"lu-lagged"`` (GMRES to rtol=1e-12, right-preconditioned by
        a MUMPS LU set up on an earlier matrix and reused while it takes few iterations:
        Newton steps and rollouts whose Jacobian moves a little per solve). Iterative presets
        run to rtol=1e-10 unless ``max_it`` caps them.

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
    def adjoint_options(self) -> KSPOptions:
        """The options of the transposed solve (the forward ones by default)."""
        return self if self.adjoint is None else self.adjoint

    def with_max_it(self, max_it: int | None) -> KSPOptions:
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
            atol = 0.0 if self.atol is None else self.atol      # scale-free: rtol alone decides
            max_it = DEFAULT_CONVERGED_MAX_IT
        divtol = 1e300 if self.divtol is None else self.divtol
        return {"rtol": rtol, "atol": atol, "divtol": divtol, "max_it": max_it}

    def skips_residual_norm(self) -> bool:
        """Whether a solve may run with NORM_NONE (pure cap, no tolerance asked)."""
        return (self.capped and self.rtol is None and self.atol is None and self.divtol is None
                and self.ksp_type in NORM_FREE_KSP_TYPES and "ksp_norm_type" not in self.petsc_options)


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
    # PETSc's own factorisation on one process (create_ksp picks MUMPS under MPI).
    "cholesky": KSPOptions(ksp_type="preonly", pc_type="cholesky", max_it=None),
    # GMRES on the current matrix, preconditioned by the MUMPS LU of an earlier one (right
    # preconditioning: the tolerance is on the true residual).
    "lu-lagged": KSPOptions(ksp_type="gmres", pc_type="lu", gmres_restart=30, max_it=None, rtol=1e-12,
                            lag_preconditioner=True,
                            petsc_options={"pc_factor_mat_solver_type": "mumps", "ksp_pc_side": "right"}),
})

