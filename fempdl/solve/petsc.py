"""PETSc objects for :class:`~fempdl.solve.options.KSPOptions`: KSPs created under an options prefix,
set up, and destroyed with the options they put into PETSc's global database; and a PETSc matrix
as a scipy one (:func:`petsc_to_scipy`).

Options go into the database under a private prefix per solver (all removed on destroy), or under
a user's ``options_prefix`` (where options already in the database win, and only the keys this
solver added are removed, once no other live solver under that prefix uses them).

A ``petsc_options`` value PETSc refuses is named in a ValueError, whether PETSc refuses it when
the options are read (:func:`create_ksp`) or only when the preconditioner is set up
(:func:`set_up`: a factorisation package that does not exist): the option is found by trying
each on a probe solver, which costs nothing until PETSc has refused something."""
from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from fempdl.solve.options import NORM_FREE_KSP_TYPES, PRIVATE_PREFIX, KSPOptions

__all__ = ["create_ksp", "set_up", "rejected_at_set_up", "destroy_ksp", "set_norm_type", "unique_prefix",
           "petsc_to_scipy"]

# Options set under users' prefixes by live solvers: {full name: number of solvers}.
_ADDED_OPTIONS: dict[str, int] = {}
_ADDED_KEYS = "fempdl_added_options"     # the KSP attribute listing the keys it added
_CREATED_WITH = "fempdl_created_with"    # the KSP attribute holding its (options, fields), to name a refusal
# PETSc's error codes for a type or factorisation package it does not know (PETSC_ERR_ARG_UNKNOWN_TYPE,
# PETSC_ERR_MISSING_FACTOR): an option's value raises them on every rank alike, so all ranks can probe
# together. Other set-up errors may be one rank's (a zero pivot), which must not wait for the others.
_EVERY_RANK_ERRORS = (86, 92)
_counter = itertools.count()


def unique_prefix(stem: str) -> str:
    """A private options prefix no other solver of this process has, e.g. ``fempdl_ksp3_``."""
    return f"{PRIVATE_PREFIX}{stem}{next(_counter)}_"


def create_ksp(A: PETSc.Mat, options: KSPOptions, prefix: str, fields=None) -> PETSc.KSP:
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
    set_norm_type(ksp, options)
    ksp.setTolerances(**options.petsc_tolerances())
    ksp.setInitialGuessNonzero(False)
    petsc_options = dict(options.petsc_options)
    if options.pc_type in ("lu", "cholesky") and A.getNullSpace() is not None and (
            petsc_options.get("pc_factor_mat_solver_type") == "mumps" or A.getComm().getSize() > 1):
        # A singular operator (an enclosed flow's pressure constant): without null-pivot
        # detection MUMPS factorises it as if regular and returns a wrong solution.
        petsc_options.setdefault("mat_mumps_icntl_24", 1)
    db = PETSc.Options()
    if prefix.startswith(PRIVATE_PREFIX):
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
    # preconditioner is first set up, so the options stay until destroy_ksp.
    try:
        ksp.setFromOptions()
    except PETSc.Error as err:
        destroy_ksp(ksp)
        raise _rejected_option(A, options, err) from None
    ksp.setAttr(_CREATED_WITH, (options, fields))
    return ksp


def _rejected_option(A: PETSc.Mat, options: KSPOptions, err: PETSc.Error) -> ValueError:
    """The error for petsc_options PETSc refused, naming the option (found by trying each alone)."""
    for key, value in options.petsc_options.items():
        probe = PETSc.KSP().create(A.getComm())
        prefix = unique_prefix("probe")
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
            destroy_ksp(probe)
    return ValueError(f"PETSc rejected petsc_options {dict(options.petsc_options)} for ksp_type="
                      f"{options.ksp_type!r}, pc_type={options.pc_type!r} (PETSc error code {err.ierr}); check "
                      "each option's value")


def set_up(ksp: PETSc.KSP, reuse: bool) -> None:
    """KSPSetUp, and the set-up of a fieldsplit's inner solvers (otherwise done lazily
    in the first iteration); with ``reuse`` the preconditioner is kept as it is.

    Raises:
        ValueError: PETSc refused the set-up because of a ``petsc_options`` value of the
            :func:`create_ksp` options (named; other set-up errors pass unchanged)."""
    pc = ksp.getPC()
    pc.setReusePreconditioner(reuse)
    try:
        _set_up(ksp, pc, reuse)
    except PETSc.Error as err:
        blamed = rejected_at_set_up(ksp, err)
        if blamed is None:
            raise
        raise blamed from None


def _set_up(ksp: PETSc.KSP, pc: PETSc.PC, reuse: bool) -> None:
    ksp.setUp()
    pc.setUp()     # KSPSetUp leaves a changed matrix's preconditioner to the solve
    if not reuse and pc.getType() == "fieldsplit":
        # The blocks' preconditioners (e.g. the velocity block's LU) refresh in the first
        # iteration otherwise: their KSPs see the same submatrix objects, new values.
        for sub in pc.getFieldSplitSubKSP():
            sub.getPC().setUp()


def rejected_at_set_up(ksp: PETSc.KSP, err: PETSc.Error) -> ValueError | None:
    """The error naming the ``petsc_options`` entry that made the set-up of ``ksp`` (made by
    :func:`create_ksp`; also when a SNES set it up) fail with ``err``, found on probe solvers (the
    same operator and options without them, then each entry alone); None when they are not to
    blame (the set-up fails without them too, or succeeds with them all: the matrix or options
    from elsewhere; the caller re-raises PETSc's error)."""
    created = ksp.getAttr(_CREATED_WITH)
    if created is None or not created[0].petsc_options:
        return None
    options, fields = created
    A = ksp.getOperators()[0]
    if A.getComm().getSize() > 1 and err.ierr not in _EVERY_RANK_ERRORS:     # probes are collective
        return None
    if not _sets_up(A, options, {}, fields):
        return None
    where = (f"ksp_type={options.ksp_type!r}, pc_type={options.pc_type!r}; PETSc error code {err.ierr}: "
             f"{_petsc_reason(err)}")
    for key, value in options.petsc_options.items():
        if not _sets_up(A, options, {key: value}, fields):
            return ValueError(f"petsc_options[{key!r}] = {value!r} was rejected by PETSc when the solver was set up "
                              f"({where}); give a value this PETSc build takes for it, or leave the option out")
    if _sets_up(A, options, dict(options.petsc_options), fields):
        return None       # something else: an option given outside petsc_options, under a user's prefix
    return ValueError(f"petsc_options {dict(options.petsc_options)} were rejected together by PETSc when the "
                      f"solver was set up ({where}), though each alone is taken; check how they combine")


def _sets_up(A: PETSc.Mat, options: KSPOptions, petsc_options: dict, fields) -> bool:
    """Whether a probe solver with ``options`` but ``petsc_options`` sets up on ``A``."""
    probe = None
    try:
        probe = create_ksp(A, dataclasses.replace(options, petsc_options=petsc_options), unique_prefix("probe"),
                           fields)
        _set_up(probe, probe.getPC(), reuse=False)
        return True
    except (PETSc.Error, ValueError, TypeError):   # refused by PETSc, or options not valid without the others
        return False
    finally:
        if probe is not None:
            destroy_ksp(probe)


def _petsc_reason(err: PETSc.Error) -> str:
    """PETSc's own words for ``err``: the last line of its message, without the rank."""
    lines = [line.strip() for line in str(err).splitlines() if line.strip()]
    return lines[-1].split("] ", 1)[-1] if lines else f"error code {err.ierr}"


def destroy_ksp(ksp: PETSc.KSP) -> None:
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


def set_norm_type(ksp: PETSc.KSP, options: KSPOptions) -> None:
    if options.skips_residual_norm():
        ksp.setNormType(PETSc.KSP.NormType.NONE)
    elif options.ksp_type in NORM_FREE_KSP_TYPES and "ksp_norm_type" not in options.petsc_options:
        ksp.setNormType(PETSc.KSP.NormType.PRECONDITIONED if options.ksp_type != "richardson"
                        else PETSc.KSP.NormType.UNPRECONDITIONED)


def petsc_to_scipy(A: PETSc.Mat) -> sp.csr_matrix:
    """The local rows of an assembled PETSc AIJ matrix as a scipy CSR matrix (a copy)."""
    indptr, indices, data = A.getValuesCSR()
    return sp.csr_matrix((data, indices, indptr), shape=(A.getLocalSize()[0], A.getSize()[1]))
