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

from fempdl.layer.implicit_diff import ImplicitSolve, count_on_all_ranks, nonfinite_control_message, register_layer
from fempdl.iterative.batched import BatchedEngine
from fempdl.layer.unrolled_diff import UnrolledPath, unrolled_method
from fempdl.solve.options import KSPOptions
from fempdl.solve.stats import CumulativeStats, warn_at_caller
from fempdl.core.problem import Problem
from fempdl.solve.linear_system import INITIAL_GUESS, LinearSystem

__all__ = ["SolveLayer", "DIFF_MODES", "default_options", "DIRECT_MAX_DOFS"]

DIFF_MODES = ("implicit", "unrolled")
#: The most unknowns a layer without options solves directly (MUMPS LU). The fill of a 3D
#: factorisation grows like n^(4/3); beyond a few hundred thousand unknowns a converged
#: iterative solve is the safer default.
DIRECT_MAX_DOFS = 300_000


def default_options(problem: Problem) -> KSPOptions:
    """The options of ``SolveLayer(problem)``: a converged solve, never a cap (a cap is what a user
    asks for): the ``"lu"`` preset up to :data:`DIRECT_MAX_DOFS` unknowns, the converged ``"gmres"``
    preset (GMRES(30) + Jacobi to rtol 1e-10, an error if not reached) above it."""
    n = problem.V.mesh.comm.allreduce(problem.output_size)
    return KSPOptions.preset("lu" if n <= DIRECT_MAX_DOFS else "gmres")
_FLOAT_DTYPES = (torch.float32, torch.float64)


class SolveLayer(torch.nn.Module):
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
        if diff not in DIFF_MODES:
            raise ValueError(f"diff must be one of {list(DIFF_MODES)}, got {diff!r}")
        if diff == "unrolled":
            unrolled_method(options)  # validates
            if problem.V.mesh.comm.size > 1:
                raise ValueError("diff='unrolled' runs on one process; use diff='implicit' under MPI")
            if len(problem.nullspace):
                raise ValueError("diff='unrolled' does not project out the operator's null space (an enclosed "
                                 "flow's pressure constant); use diff='implicit'")
        self.problem = problem
        self.diff = diff
        self._unrolled = UnrolledPath(max_unrolled_values, memory_budget) if diff == "unrolled" else None
        self._system = LinearSystem(problem, options, batched_engine=BatchedEngine())
        # Plain values for forward, so torch.compile traces it without entering the Problem.
        self._distributed = problem.V.mesh.comm.size > 1
        self._sizes = {**{n: problem.control_size(n) for n in problem.control_names},
                       INITIAL_GUESS: problem.output_size}
        self._handle = register_layer(self)

    @property
    def system(self) -> LinearSystem:
        """The assembled system (raises once the layer is closed)."""
        if self._system is None:
            raise RuntimeError("this SolveLayer was closed (close() freed its PETSc objects); "
                               "create a new SolveLayer to solve again")
        return self._system

    @property
    def options(self) -> KSPOptions:
        return self.system.options

    @property
    def max_it(self) -> int | None:
        return self.system.max_it

    @max_it.setter
    def max_it(self, value: int | None) -> None:
        self.system.max_it = value

    @property
    def max_unrolled_values(self) -> int | None:
        """In unrolled mode, the floats the stored iterates may take before checkpointing (assignable)."""
        return None if self._unrolled is None else self._unrolled.max_values

    @max_unrolled_values.setter
    def max_unrolled_values(self, value: int | None) -> None:
        if self._unrolled is None:
            raise ValueError("max_unrolled_values applies to diff='unrolled' layers")
        self._unrolled.max_values = value

    @property
    def stats(self) -> CumulativeStats:
        return self.system.stats

    def forward(self, *positional, initial_guess: torch.Tensor | None = None, **controls: torch.Tensor) -> torch.Tensor:
        """Solve for the given controls (keyword per control name); see the module docstring.

        ``initial_guess`` ((B, n) or (n,), like the output) warm-starts the
        iterations: a capped solve then runs K iterations from it instead of from
        zero (time steppers start from the state being advanced). It is
        differentiable: exactly for Richardson + Jacobi in both modes and for
        every method in unrolled mode; in implicit mode the adjoint residual is
        the gradient (module docstring)."""
        if positional:
            names = [n for n in self._sizes if n != INITIAL_GUESS]
            raise TypeError(f"SolveLayer takes its controls as keywords, got {len(positional)} positional "
                            f"argument(s); call it as layer({', '.join(f'{n}=...' for n in names)})")
        if initial_guess is not None:
            controls = {**controls, INITIAL_GUESS: initial_guess}
        names, tensors, batch, batched = self._validate(controls)
        if self._distributed:
            self._check_ranks_agree(names, batch)
        dtype = tensors[0].dtype if tensors else torch.float64
        if any(t.dtype != dtype for t in tensors):
            dtype = torch.float64
        device = tensors[0].device if tensors else torch.device("cpu")
        if self._unrolled is not None:
            self._check_finite(names, tensors)
            t0 = time.perf_counter()
            out = self._unrolled.solve(self.system, {n: t.to(device="cpu", dtype=torch.float64)
                                                     for n, t in zip(names, tensors)}, batch)
            self.stats.layer_time += time.perf_counter() - t0
        else:
            # The operator checks the controls for NaN/inf and the float32 range of the solution.
            keep = torch.is_grad_enabled() and any(t.requires_grad for t in tensors)
            out = ImplicitSolve.apply(self._handle, names, batch, keep, dtype != torch.float64, *tensors)
        out = out.to(device=device, dtype=dtype)
        if (self._unrolled is not None and dtype != torch.float64
                and count_on_all_ranks(~torch.isfinite(out), self.problem)):
            self._report_overflow(dtype)
        return out if batched else out[0]

    def _check_ranks_agree(self, names, batch: int) -> None:
        """On a distributed mesh every rank must make the same call (the solves are collective): one
        allgather of (cap, batch, controls), and a ValueError on every rank if they differ, instead of
        ranks waiting in different collectives (a hang)."""
        comm = self.problem.V.mesh.comm
        mine = (self.max_it, batch, tuple(names))
        every = comm.allgather(mine)
        if any(call != mine for call in every):
            raise ValueError(
                "the ranks called this distributed-mesh SolveLayer differently (max_it, batch, controls by rank: "
                f"{every}); every rank must call it with the same cap, batch size and controls. A PRDP step on "
                "per-rank metrics moves the caps apart: step PRDP with the same (reduced) metric on every rank")

    def _check_finite(self, names, tensors) -> None:
        for name, t in zip(names, tensors):
            bad = count_on_all_ranks(~torch.isfinite(t.detach()), self.problem)
            if bad:
                raise ValueError(nonfinite_control_message(name, bad))

    def _report_overflow(self, dtype) -> None:
        message = (f"the solution is finite in float64 but overflows {dtype}; pass float64 controls "
                   "or rescale the problem")
        if self.options.on_failure == "warn":
            warn_at_caller(message, RuntimeWarning)
        else:
            raise OverflowError(message)

    def get_extra_state(self) -> dict:
        """The cap travels with ``state_dict()``: a saved model reloads at the K it was trained at."""
        return {"max_it": self.max_it}

    def set_extra_state(self, state: dict) -> None:
        if not isinstance(state, dict) or "max_it" not in state:
            raise ValueError(f"SolveLayer state must be a dict with 'max_it', got {state!r}")
        self.max_it = state["max_it"]

    def __getstate__(self):
        raise TypeError("a SolveLayer holds DOLFINx and PETSc objects, which cannot be pickled or deep-copied "
                        "(torch.save(model), copy.deepcopy, AveragedModel); save model.state_dict() instead (it "
                        "carries each layer's max_it) and rebuild the model, with its layers, from its Problem")

    def close(self) -> None:
        """Free the PETSc objects now (otherwise when the system is garbage collected: a system still
        referenced, ``SolveLayer(p).system``, outlives its layer)."""
        if getattr(self, "_system", None) is not None:
            self._system.destroy()
            self._system = None

    def extra_repr(self) -> str:
        if self._system is None:
            return "closed"
        o = self.options
        return (f"controls={list(self.problem.control_names)}, n={self.problem.output_size}, "
                f"ksp={o.ksp_type}+{o.pc_type}, max_it={o.max_it}, diff={self.diff!r}")

    def _validate(self, controls: dict):
        sizes = self._sizes
        unknown = [n for n in controls if n not in sizes]
        if unknown:
            raise ValueError(f"unknown control(s) {unknown}; this layer's controls are "
                             f"{[n for n in sizes if n != INITIAL_GUESS]}")
        names = tuple(n for n in sizes if n in controls)
        tensors = [controls[n] for n in names]
        batch_sizes = {}
        for name, t in zip(names, tensors):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"control {name!r} must be a torch.Tensor, got {type(t).__name__}; "
                                "wrap arrays with torch.as_tensor(..., dtype=torch.float64)")
            if t.dtype not in _FLOAT_DTYPES:
                raise TypeError(f"control {name!r} has dtype {t.dtype}; use float32 or float64 "
                                "(e.g. tensor.double())")
            n = sizes[name]
            if t.dim() not in (1, 2) or t.shape[-1] != n:
                raise ValueError(
                    f"control {name!r} has shape {tuple(t.shape)}, expected (B, {n}) or ({n},): one value per "
                    f"owned DOF of its space; a different size usually means a tensor built for another "
                    f"mesh, space or degree (see problem.control_size({name!r}))")
            if t.dim() == 2:
                if t.shape[0] == 0:
                    raise ValueError(f"control {name!r} has an empty batch (shape {tuple(t.shape)})")
                batch_sizes[name] = t.shape[0]
        if len(set(batch_sizes.values())) > 1:
            raise ValueError(f"controls have different batch sizes {batch_sizes}; "
                             "pass (B, n) tensors with one B, or (n,) tensors shared by all samples")
        devices = {t.device for t in tensors}
        if len(devices) > 1:
            raise ValueError(f"controls are on different devices {sorted(map(str, devices))}; move them to one")
        batch = next(iter(batch_sizes.values()), 1)
        return names, tensors, batch, bool(batch_sizes)
