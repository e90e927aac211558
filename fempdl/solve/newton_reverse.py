"""The two reverse passes of a Newton system: :class:`NewtonReversePass`, which a
:class:`~fempdl.solve.nonlinear_system.NonlinearSystem` holds and answers its ``adjoint`` and
``unrolled_adjoint`` with.

* :meth:`NewtonReversePass.adjoint`, the implicit adjoint at the returned states (``diff="implicit"``):
  per sample J(u)^T lam = g, then dJ/dm = -d/dm F(u, lam; m) from the problem's gradient forms.
* :meth:`NewtonReversePass.unrolled_adjoint`, the exact reverse pass of the plain Newton map that was run
  (``diff="unrolled"``): per sample and per step k = N-1 ... 0, backwards, mu = J(u_k)^{-T} u_bar, then
  u_bar <- u_bar + a dQ/du and m_bar += a dQ/dm with Q = mu^T J(u_k; m) delta_k - F(u_k, mu; m) (the
  problem's step forms), from the iterates a forward solve recorded (:class:`NewtonPath`).

Both solve with the system's transposed Jacobian (its public ``transpose_solve``); the pass owns only
the vectors the step forms assemble into.
"""
from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from fempdl.core import _dolfinx
from fempdl.solve.assembly import ControlValues, Timer, set_owned, without_bc_entries
from fempdl.solve.control_forms import ControlForms
from fempdl.solve.linear_system import INITIAL_GUESS

__all__ = ["NewtonPath", "NewtonReversePass"]


@dataclass
class NewtonPath:
    """The iterates of one call's Newton solves, for the unrolled reverse pass:
    ``iterates[i]`` is (steps_i + 1, n) for sample i (u_0 with its boundary values, ..., u_N)."""

    iterates: list
    damping: float


class NewtonReversePass:
    """The reverse passes of one Newton system (module docstring).

    Args:
        problem: the system's NonlinearProblem.
        stats: the system's cumulative Newton stats (assembly time, backward Newton steps).
        control_forms: the system's :class:`~fempdl.solve.control_forms.ControlForms` (the implicit
            gradient forms).
        transpose_solve: ``transpose_solve(u, g, exact, controls)``: assemble J(u) (``exact``: dF/du) and
            solve J^T lam = g into ``problem.lam``; ``controls``, the names of the call's controls, are
            what a singular J's message names (:meth:`NonlinearSystem.transpose_solve`).
    """

    def __init__(self, problem, stats, control_forms: ControlForms, transpose_solve: Callable):
        self.problem, self.stats = problem, stats
        self._forms, self._transpose_solve = control_forms, transpose_solve
        self._step_vectors: dict = {}        # per control name (None: the state), created on first use

    def adjoint(self, controls: Mapping[str, np.ndarray], U: np.ndarray, G: np.ndarray,
                wanted, shared=frozenset(), initial_guess: bool = False) -> dict[str, np.ndarray]:
        """Implicit control gradients dJ/dm (batch, n_m) at the states U, for incoming
        G = dJ/du (batch, n). With ``initial_guess`` the result also holds a zero
        gradient for the starting point: a solution of F(u) = 0 does not depend on it."""
        p = self.problem
        batch = G.shape[0]
        wanted = [n for n in p.input_names if n in set(wanted)]
        grads = {n: np.zeros((batch, p.control_size(n))) for n in wanted}
        if initial_guess:
            grads[INITIAL_GUESS] = np.zeros((batch, p.output_size))
        G = without_bc_entries(G, p)
        called = frozenset(controls)
        with ControlValues(p, controls, refresh=False) as ctl:
            for i in range(batch):
                ctl.set_sample(i)
                self._transpose_solve(U[i], G[i], True, called)
                for name in wanted:
                    grads[name][i] = self._forms.gradient(name)
        return grads

    def unrolled_adjoint(self, controls: Mapping[str, np.ndarray], path: NewtonPath, G: np.ndarray,
                         wanted, initial_guess: bool = False) -> dict[str, np.ndarray]:
        """The exact vector-Jacobian product of the plain Newton map that produced ``path``:
        dJ/dm (batch, n_m) for m in ``wanted`` and, with ``initial_guess``, dJ/du_0 (batch, n)."""
        p = self.problem
        batch = G.shape[0]
        wanted = [n for n in p.input_names if n in set(wanted)]
        grads = {n: np.zeros((batch, p.control_size(n))) for n in wanted}
        a = path.damping
        G = without_bc_entries(G, p)
        called = frozenset(controls)
        with ControlValues(p, controls, refresh=False) as ctl:
            for i in range(batch):
                ctl.set_sample(i)
                iterates = path.iterates[i]
                u_bar = G[i]
                for k in range(len(iterates) - 2, -1, -1):
                    self._transpose_solve(iterates[k], u_bar, False, called)     # lam = mu_k, u = u_k
                    set_owned(p.step, (iterates[k] - iterates[k + 1]) / a, p.output_size)
                    for name in wanted:
                        grads[name][i] += a * (self._forms.network_gradient(name, p.network_cotangent_forms(name, True))
                                               if name in p.networks else
                                               self._assembled(p.step_control_form(name), name))
                    u_bar = u_bar + a * self._assembled(p.step_state_form(), None)
                    if len(p.bc_dofs):
                        u_bar[p.bc_dofs] = 0.0        # u_k takes the boundary values whatever came before
                    self.stats.backward_newton_steps += 1
                if initial_guess:
                    grads.setdefault(INITIAL_GUESS, np.zeros((batch, p.output_size)))[i] = u_bar
        return grads

    def _assembled(self, form, name: str | None) -> np.ndarray:
        """Owned values of a compiled linear form on the space of control ``name`` (None: the solution space)."""
        p = self.problem
        n = p.output_size if name is None else p.control_size(name)
        if form is None:
            return np.zeros(n)
        vec = self._step_vectors.get(name)
        if vec is None:
            vec = self._step_vectors[name] = _dolfinx.create_vector(form)
        with Timer(self.stats, "assembly_time"):
            _dolfinx.assemble_vector_into(vec, form)
        return vec.getArray(readonly=True)[:n].copy()

    def destroy(self) -> None:
        for vec in self._step_vectors.values():
            vec.destroy()
        self._step_vectors.clear()
