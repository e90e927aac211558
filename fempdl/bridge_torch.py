"""A finite-element solve as a differentiable PyTorch layer.

``SolveLayer(problem, options, diff="implicit")`` maps control tensors to the
solution's owned DOF values:

    u = S_K(m),   A(m) u = b(m) solved by the capped solver (K = ``max_it``),

and its backward pass is the implicit (adjoint) derivative

    A(m)^T lam = dJ/du   (BC entries zeroed, same solver, same cap),
    dJ/dm = -lam^T dF/dm  (assembled derivative forms, only for controls that
                           require grad).

What this gradient is: for Richardson + Jacobi it is *exactly* the
vector-Jacobian product of the K-step map with respect to right-hand-side
controls (the K-step Jacobi map on A^T is the transpose of the one on A). For
capped CG/GMRES, and for matrix controls such as kappa, it is the PRDP paper's
"implicit differentiation": an approximation of the derivative of the capped
map that converges to the exact gradient as K grows. For converged solves
(rtol reached, or LU) it is the exact gradient of the discrete solution.

A warm start ``layer(..., initial_guess=x0)`` runs the K iterations from x0
instead of zero. Its implicit gradient is the adjoint residual
dJ/du - A^T lam: exactly the derivative of the K-step Richardson + Jacobi map
with respect to x0 ((I - D^-1 A)^K, transposed), an approximation for capped
CG/GMRES that vanishes as they converge, and 0 for a direct solve.

Shapes: each control tensor is (B, n_m) or (n_m,) with n_m =
``problem.control_size(name)``; a (n_m,) tensor is shared by all samples. The
output is (B, n) if any input is batched, else (n,), n = ``problem.output_size``.
Values are owned DOFs in DOLFINx's DOF order (``problem.dof_coordinates``).
Computation is in float64; the output has the inputs' floating dtype (float64
if they differ) and their device (CUDA tensors are solved on the CPU).

In implicit mode the layer composes with torch.func (grad, vjp, jacrev; vmap
folds the mapped dimension into the native batch: one solve call) and with
torch.compile (each solve and each adjoint solve is one opaque operator, no
graph break); see :mod:`fempdl.layer.implicit_diff`.
"""
from __future__ import annotations

import time

import torch

from fempdl.layer.implicit_diff import count_on_all_ranks
from fempdl.layer.system_layer import DIFF_MODES, SystemLayer, check_diff
from fempdl.iterative.batched import BatchedEngine
from fempdl.layer.unrolled_diff import UnrolledPath, unrolled_method
from fempdl.solve.options import DIRECT_MAX_DOFS, KSPOptions, default_options
from fempdl.core.problem import Problem
from fempdl.solve.linear_system import LinearSystem

__all__ = ["SolveLayer", "DIFF_MODES", "default_options", "DIRECT_MAX_DOFS"]


class SolveLayer(SystemLayer):
    """Differentiable capped linear solve of a :class:`fempdl.Problem`.

    Args:
        problem: the variational problem; its controls become keyword inputs.
        options: :class:`KSPOptions`, or a preset name (``"jacobi"``, ``"cg"``,
            ``"gmres"``, ``"lu"``; converged unless ``KSPOptions.preset(name,
            max_it=K)`` caps them). Default (:func:`default_options`): a solution,
            never a cap: LU where a direct solve fits, else GMRES to rtol 1e-10.
        diff: ``"implicit"`` (adjoint solve with the same cap) or ``"unrolled"``
            (autograd through the K iterations: the exact derivative of the
            capped iterate; Richardson, CG and GMRES(m) with Jacobi or no
            preconditioner; controls that enter the right-hand side affinely
            (f, u0) and one control the matrix is affine in (kappa), with zero
            Dirichlet values).
        max_unrolled_values: in unrolled mode, the number of floats the stored
            iterates may take (``unrolled.stored_values``: up to about K * B * n * 5);
            above it the iterations are checkpointed (about 2 sqrt(K) states
            kept, recomputed in backward), and a call that cannot fit even so
            is refused with a MemoryError naming the least bound that works
            (``unrolled.checkpointed_values``). ``None``: no bound.
        memory_budget: in unrolled mode, the bytes the stored iterates may
            take at most; a call that would keep more is refused with a
            MemoryError before it starts. ``None``: half the memory available
            at the call (:func:`fempdl.core.resources.memory_budget`).

    Attributes:
        max_it: the iteration cap K; assign to move it between calls (PRDP does).
        stats: cumulative :class:`~fempdl.ksp_adjoint.CumulativeStats` over all
            samples: forward/backward iterations, solves, solve time, layer time.

    Example:
        >>> layer = SolveLayer(prob, KSPOptions(max_it=20))
        >>> u = layer(f=f_batch)            # (B, n)
        >>> layer.max_it = 40
    """

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
        self.diff = diff
        self._unrolled = UnrolledPath(max_unrolled_values, memory_budget) if diff == "unrolled" else None
        self._init_system(problem, LinearSystem(problem, options, batched_engine=BatchedEngine()))

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
        names, tensors, batch, batched, dtype, device = self._inputs(positional, initial_guess, controls)
        if self._unrolled is not None:
            self._check_finite(names, tensors)
            t0 = time.perf_counter()
            given = {n: t.to(device="cpu", dtype=torch.float64) for n, t in zip(names, tensors)}
            training = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
            out = self.solve_healthy(lambda: self._unrolled.solve(self.system, given, batch), training)
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
