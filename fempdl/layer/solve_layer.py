"""A finite-element solve as a differentiable PyTorch layer: :class:`SolveLayer`.

    forward   u = S_K(m):        A(m) u = b(m), capped solve (K = ``max_it``)
    backward  A(m)^T lam = dJ/du  (same solver, same cap; Dirichlet entries zeroed)
              dJ/dm = -lam^T dF/dm

The gradient is exact for Richardson + Jacobi with right-hand-side controls
(the K-step Jacobi map on A^T is the transpose of the one on A) and for
converged solves; for capped CG/GMRES and matrix controls it is the PRDP
paper's implicit differentiation, exact in the limit of large K.
``diff="unrolled"`` differentiates the K iterations themselves.
Reference: ``docs/api/solve-layer.md``; the public import path is
:mod:`fempdl.bridge_torch`.
"""
from __future__ import annotations

import time

import torch

from fempdl.core.problem import Problem
from fempdl.iterative.batched import BatchedEngine
from fempdl.layer.implicit_diff import count_on_all_ranks
from fempdl.layer.system_layer import SystemLayer, check_diff
from fempdl.layer.unrolled_diff import UnrolledPath, unrolled_method
from fempdl.solve.default_solver import default_options
from fempdl.solve.linear_system import LinearSystem
from fempdl.solve.options import STATIONARY_KSP_TYPES, KSPOptions

__all__ = ["SolveLayer"]


class SolveLayer(SystemLayer):
    """Differentiable capped linear solve of a :class:`fempdl.Problem`.

    Args:
        problem: the variational problem; its controls become keyword inputs.
        options: :class:`KSPOptions` or a preset name; default
            (:func:`~fempdl.solve.default_solver.default_options`) a solution, never a cap: LU
            while the factorisation is cheap, else CG + AMG, a Schur fieldsplit, GMRES + GAMG or
            GMRES + ILU(0) by the problem's symmetry, fields and near null space.
        diff: ``"implicit"`` (adjoint solve with the same cap) or ``"unrolled"``
            (autograd through the K iterations: Richardson, CG and GMRES(m) with
            Jacobi or no preconditioner, one process).
        max_unrolled_values: unrolled mode: floats the stored iterates may take
            before they are checkpointed; ``None``: no bound.
        memory_budget: unrolled mode: bytes the stored iterates may take, else
            MemoryError before the call starts; ``None``: half the memory available.

    Shapes: each control (B, n_m) or (n_m,) (shared by the batch), n_m =
    ``problem.control_size(name)``; output (B, n) if any input is batched, else
    (n,), n = ``problem.output_size``, owned DOFs in DOLFINx's order. Float64
    inside; the output takes the inputs' dtype and device.

    Attributes:
        max_it: the cap K; assign between calls (PRDP does).
        stats: :class:`~fempdl.solve.stats.CumulativeStats` over all samples.
    """

    measures_adjoint_health = True         # a capped adjoint whose residual grew is garbage too

    def __init__(self, problem: Problem, options: KSPOptions | str | None = None, *,
                 diff: str = "implicit", max_unrolled_values: int | None = None,
                 memory_budget: int | None = None):
        super().__init__()
        if not isinstance(problem, Problem):
            raise TypeError(f"problem must be a fempdl.Problem, got {type(problem).__name__}; "
                            "build one with fempdl.forms.<pde>.problem(...) or fempdl.Problem(a, L, bcs, controls)")
        if options is None:
            options = default_options(problem)
        elif isinstance(options, str):
            options = KSPOptions.preset(options)
        elif not isinstance(options, KSPOptions):
            raise TypeError(f"options must be KSPOptions or a preset name, got {type(options).__name__}")
        check_diff(diff)
        if diff == "unrolled":
            unrolled_method(options)  # validates
            if problem.V.mesh.comm.size > 1:
                raise ValueError("diff='unrolled' runs on one process; use diff='implicit' under MPI")
            if len(problem.nullspace):
                raise ValueError("diff='unrolled' does not project out the operator's null space (an enclosed "
                                 "flow's pressure constant); use diff='implicit'")
            if problem.networks:
                raise ValueError(f"diff='unrolled' differentiates the iterations through assembled matrix "
                                 f"derivatives, which a network in the form ({sorted(problem.networks)}) has none "
                                 "of; use diff='implicit' (exact at a converged or direct solve)")
        self.diff = diff
        self._unrolled = UnrolledPath(max_unrolled_values, memory_budget) if diff == "unrolled" else None
        self._init_system(problem, LinearSystem(problem, options, batched_engine=BatchedEngine()))

    def _stationary_cap(self) -> bool:
        return self.options.capped and self.options.ksp_type in STATIONARY_KSP_TYPES

    @property
    def max_unrolled_values(self) -> int | None:
        """In unrolled mode, the floats the stored iterates may take before checkpointing (assignable)."""
        return None if self._unrolled is None else self._unrolled.max_values

    @max_unrolled_values.setter
    def max_unrolled_values(self, value: int | None) -> None:
        if self._unrolled is None:
            raise ValueError("max_unrolled_values applies to diff='unrolled' layers")
        self._unrolled.max_values = value

    def forward(self, *positional, initial_guess: torch.Tensor | None = None, **controls: torch.Tensor) -> torch.Tensor:
        """Solve for the given controls (keyword per control name); see the module docstring.

        ``initial_guess`` ((B, n) or (n,), like the output) warm-starts the
        iterations: a capped solve then runs K iterations from it instead of from
        zero (time steppers start from the state being advanced). It is
        differentiable: exactly for Richardson + Jacobi in both modes and for
        every method in unrolled mode; in implicit mode the adjoint residual is
        the gradient (module docstring)."""
        if self.route is not None:                       # reference physics, or a probe (fempdl.layer.reference)
            return self.route(*positional, initial_guess=initial_guess, **controls)
        names, tensors, batch, batched, dtype, device = self._inputs(positional, initial_guess, controls)
        if self._unrolled is not None:
            self._check_finite(names, tensors)
            t0 = time.perf_counter()
            given = {n: t.to(device="cpu", dtype=torch.float64) for n, t in zip(names, tensors)}
            training = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
            out = self.solve_healthy(lambda health: self._unrolled.solve(self.system, given, batch, health), training)
            self.stats.layer_time += time.perf_counter() - t0
        else:
            out = self._implicit(names, tensors, batch, dtype)
        out = out.to(device=device, dtype=dtype)
        if (self._unrolled is not None and dtype != torch.float64
                and count_on_all_ranks(~torch.isfinite(out), self.problem)):
            self._report_overflow(dtype)
        return out if batched else out[0]

    def extra_repr(self) -> str:
        if self._system is None:
            return "closed"
        o = self.options
        return (f"controls={list(self.problem.control_names)}, n={self.problem.output_size}, "
                f"ksp={o.ksp_type}+{o.pc_type}, max_it={o.max_it}, diff={self.diff!r}")
