"""A Newton solve of F(u; m) = 0 as a differentiable PyTorch layer.

``NonlinearSolveLayer(problem, options, diff="implicit")`` maps control
tensors to the owned DOF values of u_N, the N-th iterate of PETSc's SNES
(N = ``max_it``, or the step where the tolerances are met), each step's linear
solve J(u_k) du = F(u_k) by the inner :class:`KSPOptions` (capped or converged).

Gradients, exactly:

* ``diff="implicit"``: at the returned state u, solve J(u)^T lam = dJ/du (BC
  entries zeroed; the inner solve's adjoint options, capped or not) and return
  dJ/dm = -d/dm F(u, lam; m). This is the exact gradient of the discrete
  solution when Newton converged; for a capped Newton (or a capped inner
  solve) it is the implicit-function approximation, evaluated at the iterate.
  A warm start's gradient is 0: a solution does not depend on where Newton
  started. Composes with torch.func and torch.compile as the linear layer does
  (one opaque operator per solve and per adjoint).
* ``diff="unrolled"``: the exact derivative of the N-step plain Newton map
  that was computed, with respect to the controls and the warm start
  (:mod:`fempdl.layer.newton_unrolled`); needs ``snes_type="newton"`` and an
  exact inner step (a direct or converged inner solve), and takes at least one
  step even from a solution.

Second derivatives are refused with a RuntimeError in both modes (the
backward is a first-order adjoint); forward-mode transforms (torch.func.jvp,
hessian) stop with PyTorch's NotImplementedError. The unrolled map runs eagerly
under torch.compile and refuses torch.func. Shapes: controls (B, n_m) or
shared (n_m,); ``initial_guess`` (B, n) or (n,); the output (B, n) if any input
is batched, else (n,), in float64 unless every input is float32.
"""
from __future__ import annotations

import dataclasses

from mpi4py import MPI
import torch

from fempdl.core.checks import check_int
from fempdl.core.nonlinear_problem import NonlinearProblem
from fempdl.core.resources import format_bytes, memory_budget
from fempdl.layer.implicit_diff import count_on_all_ranks
from fempdl.layer.newton_unrolled import UnrolledNewton, check_unrolled_newton, stored_values
from fempdl.layer.system_layer import SystemLayer, check_diff
from fempdl.solve.caps import Caps
from fempdl.solve.default_solver import default_options
from fempdl.solve.newton_options import NewtonOptions
from fempdl.solve.newton_stats import NewtonCumulativeStats
from fempdl.solve.newton_stop import NewtonMode
from fempdl.solve.nonlinear_system import NonlinearSystem

__all__ = ["NonlinearSolveLayer"]


class NonlinearSolveLayer(SystemLayer):
    """Differentiable (capped) Newton solve of a :class:`fempdl.NonlinearProblem`.

    Args:
        problem: the nonlinear problem; its controls become keyword inputs.
        options: :class:`NewtonOptions` (default: converged plain Newton to rtol
            1e-10, atol 1e-12). Its ``ksp=None`` takes the
            linear layer's default inner solve (LU where it fits).
        diff: ``"implicit"`` or ``"unrolled"`` (module docstring).
        max_unrolled_values: in unrolled mode, the floats the kept iterates may
            take ((N + 1) * B * n per call); a call that needs more is refused
            with a MemoryError before it starts. ``None``: no bound but the
            memory's: a call whose iterates would exceed half the memory
            available at the call is refused likewise.
        memory_budget: in unrolled mode, the bytes a machine's kept iterates may take
            (those of its ranks together); a call that needs more is refused before it
            starts. ``None``: half the memory available at the call.

    Attributes:
        max_it: the Newton cap N (``None``: converged); assign to move it (PRDP does).
        inner_max_it: the inner solve's cap K (``None``: converged); assign to move it.
        stats: :class:`~fempdl.solve.newton_stats.NewtonCumulativeStats`: Newton
            steps and inner iterations, forward and backward, counted apart.
    """

    def __init__(self, problem: NonlinearProblem, options: NewtonOptions | None = None, *,
                 diff: str = "implicit", max_unrolled_values: int | None = None,
                 memory_budget: int | None = None):
        super().__init__()
        if not isinstance(problem, NonlinearProblem):
            raise TypeError(f"problem must be a fempdl.NonlinearProblem, got {type(problem).__name__}; a linear "
                            "fempdl.Problem goes into a SolveLayer")
        if options is None:
            options = NewtonOptions()
        elif not isinstance(options, NewtonOptions):
            raise TypeError(f"options must be NewtonOptions, got {type(options).__name__}")
        if options.ksp is None:
            options = dataclasses.replace(options, ksp=default_options(problem))
        check_diff(diff)
        if diff == "unrolled":
            check_unrolled_newton(options)
        for name, value in (("max_unrolled_values", max_unrolled_values), ("memory_budget", memory_budget)):
            if value is not None and diff != "unrolled":
                raise ValueError(f"{name} applies to diff='unrolled' layers")
        if memory_budget is not None:
            check_int("memory_budget", memory_budget, minimum=1)
        self.diff = diff
        self.max_unrolled_values, self.memory_budget = max_unrolled_values, memory_budget
        # Implicit: the cap is a budget (a solve stops at its tolerances before it); unrolled: exactly N steps,
        # and at least one even from a solution, where the map is not the identity nearby.
        self._init_system(problem, NonlinearSystem(problem, options, mode=NewtonMode.for_diff(diff)))

    second_derivative_message = (
        "second derivatives through NonlinearSolveLayer are not implemented: both its implicit and its unrolled "
        "backward are first-order adjoints, so a Hessian-vector product or a gradient of a gradient would miss "
        "the layer's second-order terms. Use finite differences of the first-order gradient")

    @property
    def inner_max_it(self) -> int | None:
        return self.system.inner_max_it

    @inner_max_it.setter
    def inner_max_it(self, value: int | None) -> None:
        options = self.system.options.with_inner_max_it(value)      # validates
        if self.diff == "unrolled":
            check_unrolled_newton(options)
        self.system.options = options                               # built once, checked once

    counts_newton_steps = True

    def _check_caps(self, caps: Caps) -> None:
        # Both caps are checked before either moves: refused caps leave the layer as it was.
        options = self.system.options.with_max_it(caps.max_it).with_inner_max_it(caps.inner_max_it)
        if self.diff == "unrolled":
            check_unrolled_newton(options)

    @property
    def stats(self) -> NewtonCumulativeStats:
        """Newton steps and inner iterations of every solve of this layer."""
        return self.system.stats

    def forward(self, *positional, initial_guess: torch.Tensor | None = None, **controls: torch.Tensor) -> torch.Tensor:
        """Solve for the given controls (keyword per control name) from ``initial_guess``
        (zero by default; its Dirichlet entries are replaced by the boundary values)."""
        if self.route is not None:                       # reference physics, or a probe (fempdl.layer.reference)
            return self.route(*positional, initial_guess=initial_guess, **controls)
        names, tensors, batch, batched, dtype, device = self._inputs(positional, initial_guess, controls)
        if self.diff == "unrolled":
            self._check_memory(batch)
            out = _unrolled(self, names, batch, [t.to(device="cpu", dtype=torch.float64) for t in tensors])
            if dtype != torch.float64 and count_on_all_ranks(~torch.isfinite(out.to(dtype)), self.problem):
                self._report_overflow(dtype)
        else:
            out = self._implicit(names, tensors, batch, dtype)
        out = out.to(device=device, dtype=dtype)
        return out if batched else out[0]

    def _check_memory(self, batch: int) -> None:
        """Refuse a call, before its first step and on every rank alike, whose kept iterates would exceed
        ``max_unrolled_values`` on a rank or half the memory available on a machine (the sum of the
        iterates of that machine's ranks): a high Newton cap would otherwise grow until the machine
        runs out of memory."""
        needed = stored_values(self.options, batch, self.problem.output_size)
        mine = (MPI.Get_processor_name(), needed, memory_budget() if self.memory_budget is None else self.memory_budget)
        comm = self.problem.V.mesh.comm
        every = comm.allgather(mine) if comm.size > 1 else [mine]
        most = max(values for _, values, _ in every)
        if self.max_unrolled_values is not None and most > self.max_unrolled_values:
            raise MemoryError(f"an unrolled Newton call would keep {most} values ((steps + 1) * batch * n, "
                              f"steps = {self.options.step_limit}, batch = {batch}), more than "
                              f"max_unrolled_values={self.max_unrolled_values}; {self._memory_fix()}")
        for host in dict.fromkeys(name for name, _, _ in every):
            kept = 8 * sum(values for name, values, _ in every if name == host)
            budget = min(limit for name, _, limit in every if name == host)
            if kept > budget:
                steps = self.options.step_limit
                where = f" on the {sum(name == host for name, _, _ in every)} ranks of {host}" if comm.size > 1 else ""
                raise MemoryError(
                    f"an unrolled Newton call would keep {format_bytes(kept)} of iterates for backward{where} "
                    f"((steps + 1) * batch * n float64 values, steps = {steps}, batch = {batch}, "
                    f"n = {kept // (8 * (steps + 1) * batch)}), more than "
                    + ("half the memory available now" if self.memory_budget is None else "memory_budget")
                    + f" ({format_bytes(budget)}); {self._memory_fix()}")

    def _memory_fix(self) -> str:
        cap = (f"cap Newton lower (max_it={self.options.max_it})" if self.options.max_it is not None
               else f"lower NewtonOptions.converged_max_it={self.options.converged_max_it}")
        return f"{cap}, pass fewer samples per call, or use diff='implicit' (it keeps one state per sample)"

    def extra_repr(self) -> str:
        if self._system is None:
            return "closed"
        o = self.options
        return (f"controls={list(self.problem.control_names)}, n={self.problem.output_size}, "
                f"snes={o.snes_type}, max_it={o.max_it}, ksp={o.ksp.ksp_type}+{o.ksp.pc_type}, "
                f"inner_max_it={o.ksp.max_it}, diff={self.diff!r}")


@torch.compiler.disable
def _unrolled(layer: NonlinearSolveLayer, names: tuple, batch: int, tensors: list) -> torch.Tensor:
    """The unrolled Newton map, run eagerly: torch.compile breaks its graph here (the iterates it keeps
    are not a traceable operator), so a compiled model around an unrolled layer still trains."""
    if any(torch._C._functorch.is_functorch_wrapped_tensor(t) for t in tensors):
        raise RuntimeError("a diff='unrolled' NonlinearSolveLayer does not compose with torch.func (grad, vjp, "
                           "jacrev, vmap): its backward replays the iterates of one autograd call. Use "
                           "loss.backward(), or diff='implicit', which composes with torch.func")
    return UnrolledNewton.apply(layer, names, batch, *tensors)

