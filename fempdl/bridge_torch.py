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
"""
from __future__ import annotations

import time

import numpy as np
import torch
from torch.autograd.function import once_differentiable

from fempdl import unrolled
from fempdl.batched import BatchedEngine
from fempdl.ksp_adjoint import CumulativeStats, KSPOptions, capped_solve_stats, warn_at_caller
from fempdl.problem import Problem
from fempdl.sparse import SparseOperator
from fempdl.system import INITIAL_GUESS, LinearSystem

__all__ = ["SolveLayer", "DIFF_MODES"]

DIFF_MODES = ("implicit", "unrolled")
# KSP/PC combinations whose K-step iterate fempdl.unrolled reproduces.
_UNROLLED_METHODS = {("richardson", "jacobi"): "jacobi", ("richardson", "none"): "jacobi",
                     ("cg", "jacobi"): "cg", ("cg", "none"): "cg",
                     ("gmres", "jacobi"): "gmres", ("gmres", "none"): "gmres"}
_FLOAT_DTYPES = (torch.float32, torch.float64)


class SolveLayer(torch.nn.Module):
    """Differentiable capped linear solve of a :class:`fempdl.Problem`.

    Args:
        problem: the variational problem; its controls become keyword inputs.
        options: :class:`KSPOptions`, or a preset name (``"jacobi"``, ``"cg"``,
            ``"gmres"``, ``"lu"``). Default: Richardson + Jacobi capped at 20.
        diff: ``"implicit"`` (adjoint solve with the same cap) or ``"unrolled"``
            (autograd through the K iterations: the exact derivative of the
            capped iterate; Richardson, CG and GMRES(m) with Jacobi or no
            preconditioner; controls that enter the right-hand side affinely
            (f, u0) and one control the matrix is affine in (kappa), with zero
            Dirichlet values).
        max_unrolled_values: in unrolled mode, the number of floats the stored
            iterates may take (about K * B * n * 2-5); above it the iterations
            are checkpointed (recomputed in backward). ``None``: no bound.
        memory_budget: in unrolled mode, the bytes the stored iterates may
            take at most; a call that would keep more is refused with a
            MemoryError before it starts. ``None``: half the memory available
            at the call (:func:`fempdl.resources.memory_budget`).

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
            options = KSPOptions(max_it=20)
        elif isinstance(options, str):
            options = KSPOptions.preset(options)
        elif not isinstance(options, KSPOptions):
            raise TypeError(f"options must be KSPOptions or a preset name, got {type(options).__name__}")
        if diff not in DIFF_MODES:
            raise ValueError(f"diff must be one of {list(DIFF_MODES)}, got {diff!r}")
        if diff == "unrolled":
            _unrolled_method(options)  # validates
            if problem.V.mesh.comm.size > 1:
                raise ValueError("diff='unrolled' runs on one process; use diff='implicit' under MPI")
            if len(problem.nullspace):
                raise ValueError("diff='unrolled' does not project out the operator's null space (an enclosed "
                                 "flow's pressure constant); use diff='implicit'")
        self.problem = problem
        self.diff = diff
        self.max_unrolled_values = max_unrolled_values
        self.memory_budget = memory_budget
        self._unrolled_cache = None
        self._unrolled_jacobians: dict = {}
        self._system = LinearSystem(problem, options, batched_engine=BatchedEngine())

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
    def stats(self) -> CumulativeStats:
        return self.system.stats

    def forward(self, *, initial_guess: torch.Tensor | None = None, **controls: torch.Tensor) -> torch.Tensor:
        """Solve for the given controls (keyword per control name); see the module docstring.

        ``initial_guess`` ((B, n) or (n,), like the output) warm-starts the
        iterations: a capped solve then runs K iterations from it instead of from
        zero (time steppers start from the state being advanced). It is
        differentiable: exactly for Richardson + Jacobi in both modes and for
        every method in unrolled mode; in implicit mode the adjoint residual is
        the gradient (module docstring)."""
        if initial_guess is not None:
            controls = {**controls, INITIAL_GUESS: initial_guess}
        names, tensors, batch, batched = self._validate(controls)
        dtype = tensors[0].dtype if tensors else torch.float64
        if any(t.dtype != dtype for t in tensors):
            dtype = torch.float64
        device = tensors[0].device if tensors else torch.device("cpu")
        if self.diff == "unrolled":
            out = self._unrolled(names, tensors, batch)
        else:
            out = _SolveFunction.apply(self, names, batch, *tensors)
        out = out.to(device=device, dtype=dtype)
        if dtype != torch.float64 and _count_on_all_ranks(~torch.isfinite(out), self.problem):
            self._report_overflow(dtype)
        return out if batched else out[0]

    def _unrolled(self, names: tuple, tensors: list, batch: int) -> torch.Tensor:
        """u = X_K^T, X_K the K-step iterate on A(m) X = R, R = b_base + sum_m C_m m^T, all in torch."""
        t0 = time.perf_counter()
        options = self.options
        if not options.capped:
            raise ValueError("diff='unrolled' differentiates a capped iteration: set max_it")
        given = dict(zip(names, (t.to(device="cpu", dtype=torch.float64) for t in tensors)))
        guess = given.pop(INITIAL_GUESS, None)
        names = tuple(n for n in names if n != INITIAL_GUESS)
        matrix_names = [n for n in names if n in self.problem.matrix_controls]
        rhs_names = frozenset(names) - set(matrix_names)
        A, P, b_base, mats = self._unrolled_operators(rhs_names)
        if matrix_names:
            A, P = self._unrolled_matrix(matrix_names, given)
        R = b_base.expand(-1, batch)
        for name in sorted(rhs_names):
            m = given[name]
            R = R + mats[name] @ (m.unsqueeze(1) if m.dim() == 1 else m.T)
        method = _unrolled_method(options)
        omega = float(options.petsc_options.get("ksp_richardson_scale", 1.0))
        t_solve = time.perf_counter()
        X0 = None if guess is None else (guess.unsqueeze(1) if guess.dim() == 1 else guess.T).expand(-1, batch)
        X = unrolled.solve(method, A, P if options.pc_type == "jacobi" else None, R, options.max_it,
                           omega=omega, restart=options.gmres_restart or 30, max_values=self.max_unrolled_values,
                           X0=X0, memory_budget=self.memory_budget)
        seconds = time.perf_counter() - t_solve
        finite = torch.isfinite(X).all(0)
        stats = self.system.stats
        for ok in finite.tolist():
            stats.record("forward", capped_solve_stats(options, seconds / batch, ok, "unrolled"))
        if not bool(finite.all()):
            self.system._solver.report_failure("forward", stats.last, finite=False,
                                               samples=int((~finite).sum()))
        out = X.T
        if out.requires_grad:
            out.register_hook(self._count_unrolled_backward(batch, options))
        stats.layer_time += time.perf_counter() - t0
        return out

    def _unrolled_matrix(self, matrix_names: list, given: dict):
        """A(m) and its inverse diagonal as differentiable functions of the matrix control."""
        if len(matrix_names) > 1:
            raise NotImplementedError(f"diff='unrolled' takes one matrix control at a time, got {matrix_names}")
        name = matrix_names[0]
        p = self.problem
        if name in p.rhs_controls or not p.homogeneous_bcs():
            raise NotImplementedError(
                f"diff='unrolled' with respect to {name!r} needs zero Dirichlet values and {name!r} absent "
                "from the right-hand side (else b depends on it); use diff='implicit'")
        key = ("jacobian", name)
        if key not in self._unrolled_jacobians:
            pattern, v0, J = self.system.matrix_jacobian(name)
            rows = torch.from_numpy(np.repeat(np.arange(pattern.shape[0]), np.diff(pattern.indptr)))
            cols = torch.from_numpy(pattern.indices.astype(np.int64))
            diagonal = torch.from_numpy(np.flatnonzero(pattern.indices == rows.numpy()))
            self._unrolled_jacobians[key] = (rows, cols, diagonal, torch.from_numpy(v0)[:, None],
                                             SparseOperator.from_scipy(J))
        rows, cols, diagonal, v0, J = self._unrolled_jacobians[key]
        m = given[name]
        values = v0 + J @ (m.unsqueeze(1) if m.dim() == 1 else m.T)       # (nnz, B or 1)
        d = values[diagonal]
        P = 1.0 / torch.where(d == 0, torch.ones_like(d), d)                  # PCJACOBI: zero -> 1
        return _EntryMatrix(rows, cols, values, len(d)), P

    def _count_unrolled_backward(self, batch: int, options: KSPOptions):
        def hook(grad):
            for _ in range(batch):
                self.stats.record("backward", capped_solve_stats(options, 0.0, True, "unrolled"))
            return grad
        return hook

    def _unrolled_operators(self, names: frozenset):
        """Torch copies of A, D^{-1}, b_base and C_m, rebuilt when the matrix or the names change."""
        key = (names, self.system.matrix_version)
        if self._unrolled_cache is None or self._unrolled_cache[0] != key:
            A, b_base, mats = self.system.affine_operators(names)
            key = (names, self.system.matrix_version)
            d = A.diagonal()
            P = torch.from_numpy(1.0 / np.where(d != 0.0, d, 1.0))[:, None]  # as PCJACOBI
            self._unrolled_cache = (key, (SparseOperator.from_scipy(A), P, torch.from_numpy(b_base)[:, None],
                                          {n: SparseOperator.from_scipy(C) for n, C in mats.items()}))
        return self._unrolled_cache[1]

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
        """Free the PETSc objects now (otherwise on garbage collection)."""
        if getattr(self, "_system", None) is not None:
            self._system.destroy()
            self._system = None

    def __del__(self):
        try:
            self.close()
        except Exception:  # interpreter shutdown: PETSc may already be finalised
            pass

    def extra_repr(self) -> str:
        if self._system is None:
            return "closed"
        o = self.options
        return (f"controls={list(self.problem.control_names)}, n={self.problem.output_size}, "
                f"ksp={o.ksp_type}+{o.pc_type}, max_it={o.max_it}, diff={self.diff!r}")

    def _validate(self, controls: dict):
        p = self.problem
        unknown = [n for n in controls if n not in p.control_names and n != INITIAL_GUESS]
        if unknown:
            raise ValueError(f"unknown control(s) {unknown}; this layer's controls are {list(p.control_names)}")
        names = tuple(n for n in (*p.control_names, INITIAL_GUESS) if n in controls)
        tensors = [controls[n] for n in names]
        batch_sizes = {}
        for name, t in zip(names, tensors):
            if not isinstance(t, torch.Tensor):
                raise TypeError(f"control {name!r} must be a torch.Tensor, got {type(t).__name__}; "
                                "wrap arrays with torch.as_tensor(..., dtype=torch.float64)")
            if t.dtype not in _FLOAT_DTYPES:
                raise TypeError(f"control {name!r} has dtype {t.dtype}; use float32 or float64 "
                                "(e.g. tensor.double())")
            n = p.output_size if name == INITIAL_GUESS else p.control_size(name)
            if t.dim() not in (1, 2) or t.shape[-1] != n:
                raise ValueError(
                    f"control {name!r} has shape {tuple(t.shape)}, expected (B, {n}) or ({n},): one value per "
                    f"owned DOF of its space; a different size usually means a tensor built for another "
                    f"mesh, space or degree (see problem.control_size({name!r}))")
            if t.dim() == 2:
                if t.shape[0] == 0:
                    raise ValueError(f"control {name!r} has an empty batch (shape {tuple(t.shape)})")
                batch_sizes[name] = t.shape[0]
            bad = _count_on_all_ranks(~torch.isfinite(t.detach()), p)
            if bad:
                raise ValueError(f"control {name!r} contains {bad} NaN/inf value(s); "
                                 "check the upstream network or data")
        if len(set(batch_sizes.values())) > 1:
            raise ValueError(f"controls have different batch sizes {batch_sizes}; "
                             "pass (B, n) tensors with one B, or (n,) tensors shared by all samples")
        devices = {t.device for t in tensors}
        if len(devices) > 1:
            raise ValueError(f"controls are on different devices {sorted(map(str, devices))}; move them to one")
        batch = next(iter(batch_sizes.values()), 1)
        return names, tensors, batch, bool(batch_sizes)


class _SolveFunction(torch.autograd.Function):
    """autograd.Function around LinearSystem; all non-tensor state lives in the layer."""

    @staticmethod
    def forward(ctx, layer: SolveLayer, names: tuple, batch: int, *tensors):
        t0 = time.perf_counter()
        shared = frozenset(n for n, t in zip(names, tensors) if t.dim() == 1)
        arrays = _batched_arrays(names, tensors, batch)
        guess = arrays.pop(INITIAL_GUESS, None)
        U = layer.system.solve(arrays, batch, shared, initial_guess=guess,
                               keep_matrices=any(ctx.needs_input_grad[3:]))
        out = torch.from_numpy(U)
        # Saved through autograd so that an in-place change of an input or of the
        # output before backward raises autograd's error instead of corrupting
        # the gradient (backward re-assembles with the controls and u).
        ctx.save_for_backward(*tensors, out)
        ctx.layer, ctx.names, ctx.batch, ctx.shared = layer, names, batch, shared
        ctx.inputs = [(t.shape, t.dtype, t.device) for t in tensors]
        layer.stats.layer_time += time.perf_counter() - t0
        return out

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out):
        t0 = time.perf_counter()
        layer, names = ctx.layer, ctx.names
        wanted = [n for n, need in zip(names, ctx.needs_input_grad[3:]) if need]
        grads = {}
        if wanted:
            G = _to_numpy(grad_out)
            bad = _count_on_all_ranks(~np.isfinite(G), layer.problem)
            if bad:
                raise ValueError(f"the gradient flowing back into SolveLayer contains {bad} NaN/inf "
                                 "value(s); the loss or the layers after this one produced them")
            *tensors, out = ctx.saved_tensors
            arrays = _batched_arrays(names, tensors, ctx.batch)
            arrays.pop(INITIAL_GUESS, None)
            grads = layer.system.adjoint(arrays, out.numpy(), G, [n for n in wanted if n != INITIAL_GUESS],
                                         ctx.shared, initial_guess=INITIAL_GUESS in wanted)
        out = []
        for name, (shape, dtype, device) in zip(names, ctx.inputs):
            g = grads.get(name)
            if g is None:
                out.append(None)
                continue
            g = torch.from_numpy(g)
            g = g.sum(0) if len(shape) == 1 else g  # a shared (n,) control collects all samples
            out.append(g.to(device=device, dtype=dtype))
        layer.stats.layer_time += time.perf_counter() - t0
        return (None, None, None, *out)


class _EntryMatrix:
    """A sparse matrix per column of X, from differentiable entry values (nnz, B)
    on a fixed pattern: (A @ X)[:, b] = A_b X[:, b]."""

    def __init__(self, rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, n: int):
        self.rows, self.cols, self.values, self.n = rows, cols, values, n

    @property
    def requires_grad(self) -> bool:
        return self.values.requires_grad

    def __matmul__(self, X: torch.Tensor) -> torch.Tensor:
        return _EntryMatMul.apply(self.values, X, self.rows, self.cols, self.n)


class _EntryMatMul(torch.autograd.Function):
    """(A_b X[:, b])_b from entries (nnz, B or 1); keeps values and X (n, B),
    not the (nnz, B) products autograd would keep through index_add."""

    @staticmethod
    def forward(ctx, values, X, rows, cols, n):
        ctx.save_for_backward(values, X)
        ctx.rows, ctx.cols, ctx.n = rows, cols, n
        return torch.zeros(n, X.shape[1], dtype=X.dtype).index_add_(0, rows, values * X[cols])

    @staticmethod
    def backward(ctx, grad):
        values, X = ctx.saved_tensors
        rows, cols = ctx.rows, ctx.cols
        grad_values = grad_X = None
        if ctx.needs_input_grad[0]:
            grad_values = grad[rows] * X[cols]                              # d(A_b x_b)/d a_ij = x_j
            if values.shape[1] == 1 and grad_values.shape[1] > 1:
                grad_values = grad_values.sum(1, keepdim=True)              # shared matrix
        if ctx.needs_input_grad[1]:
            grad_X = torch.zeros_like(grad).index_add_(0, cols, values * grad[rows])  # A_b^T g_b
            if X.shape[1] == 1 and grad.shape[1] > 1:
                grad_X = grad_X.sum(1, keepdim=True)
        return grad_values, grad_X, None, None, None


def _unrolled_method(options: KSPOptions) -> str:
    method = _UNROLLED_METHODS.get((options.ksp_type, options.pc_type))
    if method is None:
        raise ValueError(f"diff='unrolled' supports {sorted(f'{k}+{p}' for k, p in _UNROLLED_METHODS)}, "
                         f"got {options.ksp_type}+{options.pc_type}; use diff='implicit' for it")
    extra = set(options.petsc_options) - {"ksp_richardson_scale"}
    if extra or any(v is not None for v in (options.rtol, options.atol, options.divtol)):
        raise ValueError("diff='unrolled' runs a pure cap: no rtol/atol/divtol and no petsc_options "
                         f"other than ksp_richardson_scale (got {sorted(extra) or 'a tolerance'})")
    return method


def _count_on_all_ranks(mask, problem: Problem) -> int:
    """Number of True entries over all ranks: every rank must take the same branch
    (raise, or go on into collective solves)."""
    return problem.V.mesh.comm.allreduce(int(mask.sum()))


def _batched_arrays(names, tensors, batch: int) -> dict:
    """float64 arrays (batch, n_m) per control; shared (n_m,) controls as broadcast views."""
    return {n: np.broadcast_to(_to_numpy(t), (batch, t.shape[-1])) for n, t in zip(names, tensors)}


def _to_numpy(t: torch.Tensor) -> np.ndarray:
    return t.detach().to(device="cpu", dtype=torch.float64).numpy()
