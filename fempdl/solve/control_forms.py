"""The forms a Problem's controls bring, assembled and kept while their inputs keep their values.

:class:`ControlForms` holds, for one :class:`~fempdl.solve.linear_system.LinearSystem`: the base
right-hand side b(0) of each set of affine controls (lifting and boundary values included), the
matrices C_m = dL/dm of affine right-hand-side controls (PETSc, and scipy for batched products),
and the vectors of the controls' gradient forms. A fingerprint of the coefficients and constants
each was assembled with detects a user's edit and triggers reassembly.
"""
from __future__ import annotations

from collections.abc import Callable

import numpy as np
import scipy.sparse as sp
from petsc4py import PETSc

from fempdl.core import _dolfinx, matrices
from fempdl.core.problem import Problem
from fempdl.solve.assembly import ControlValues, fingerprint, fingerprint_matches
from fempdl.solve.petsc import petsc_to_scipy

__all__ = ["ControlForms"]


class ControlForms:
    """Cached assemblies of ``problem``'s control forms; ``template`` is a vector of the right-hand
    side's layout, ``assembling()`` a context manager that times assembly."""

    def __init__(self, problem: Problem, template: PETSc.Vec, assembling: Callable):
        self.problem = problem
        self._template, self._assembling = template, assembling
        self._comm = problem.V.mesh.comm
        self._base: dict = {}                  # frozenset(names) -> (Vec, fingerprint)
        self._matrices: dict = {}              # name -> (Mat, vec on m, vec on V, fingerprint)
        self._scipy: dict = {}                 # name -> (fingerprint, scipy C_m, C_m^T)
        self._gradients: dict = {}             # name -> ghosted Vec on M

    def base_rhs(self, names: frozenset, ctl: ControlValues) -> PETSc.Vec:
        """b with the passed affine controls set to zero (lifting and BC values included)."""
        p = self.problem
        with ctl.zeroed(names):
            cached = self._base.get(names)
            if cached is not None and fingerprint_matches(cached[1], p.rhs_inputs(), self._comm):
                return cached[0]
            vec = cached[0] if cached is not None else self._template.duplicate()
            with self._assembling():
                _dolfinx.assemble_vector_into(vec, p.L_form, p.a_form, p.bcs)
            self._base[names] = (vec, fingerprint(p.rhs_inputs()))
        return vec

    def rhs_matrix(self, name: str):
        """(C_m, input vector, output vector, fingerprint), reassembled when its inputs change."""
        p = self.problem
        inputs = p.rhs_matrix_inputs(name)
        cached = self._matrices.get(name)
        if cached is not None and fingerprint_matches(cached[3], inputs, self._comm):
            return cached
        form = p.rhs_matrix_form(name)
        if cached is None:
            C = matrices.create_matrix(form)
            vin, out = C.createVecs()
        else:
            C, vin, out, _ = cached
        with self._assembling():
            matrices.assemble_matrix_into(C, form)
        entry = (C, vin, out, fingerprint(inputs))
        self._matrices[name] = entry
        return entry

    def rhs_matrix_scipy(self, name: str, transpose: bool = False):
        """C_m (or with ``transpose`` C_m^T, (n_m, n)) as scipy CSR, refreshed with the PETSc matrix of
        :meth:`rhs_matrix`."""
        entry = self.rhs_matrix(name)
        cached = self._scipy.get(name)
        if cached is None or cached[0] is not entry[3]:
            C = petsc_to_scipy(entry[0])
            cached = self._scipy[name] = (entry[3], C, C.T.tocsr())   # CSR both ways: no conversion per product
        return cached[2] if transpose else cached[1]

    def affine_parts(self, names: frozenset) -> tuple[np.ndarray, dict]:
        """The pieces of b(m) = b_base + sum_m C_m m for affine right-hand-side controls ``names``:
        (b_base (n,), {name: C_m scipy CSR (n, n_m)}), the Dirichlet rows of each C_m zeroed."""
        p = self.problem
        not_affine = sorted(names - p.affine_rhs_controls)
        if not_affine:
            raise NotImplementedError(
                f"controls {not_affine} enter the matrix or the right-hand side non-affinely "
                f"(affine controls of this problem: {sorted(p.affine_rhs_controls)})")
        with ControlValues(p, dict.fromkeys(names)) as ctl:
            b_base = self.base_rhs(names, ctl).getArray(readonly=True).copy()
        keep = np.ones(p.output_size)
        keep[p.bc_dofs] = 0.0  # BC rows of b come from the boundary data alone
        return b_base, {name: (sp.diags(keep) @ self.rhs_matrix_scipy(name)).tocsr() for name in sorted(names)}

    def affine_rhs_into(self, b: PETSc.Vec, b_base: PETSc.Vec, rhs_mats: dict, controls, i: int) -> None:
        """b = b_base + sum_m C_m m_i for sample ``i`` (``rhs_mats``: :meth:`rhs_matrix` of each control),
        the Dirichlet rows of the control part zeroed."""
        b_base.copy(b)
        bc = self.problem.bc_dofs
        for name, (C, vin, out, _) in rhs_mats.items():
            vin.setArray(controls[name][i])
            C.mult(vin, out)
            if len(bc):
                out.array_w[bc] = 0.0
            b.axpy(1.0, out)

    def affine_rhs_block(self, b_base: PETSc.Vec, controls, batch: int) -> np.ndarray:
        """(batch, n) right-hand sides b_base + sum_m C_m m_i, the Dirichlet rows of the control part zeroed."""
        n = self.problem.output_size
        R = np.zeros((n, batch))
        for name in sorted(controls):
            R += self.rhs_matrix_scipy(name) @ np.asarray(controls[name]).T
        if len(self.problem.bc_dofs):
            R[self.problem.bc_dofs] = 0.0
        R += b_base.getArray(readonly=True)[:n, None]
        return np.ascontiguousarray(R.T)

    def gradient(self, name: str) -> np.ndarray:
        """The assembled gradient form of control ``name`` (owned values; u and lam set by the caller); for a
        network, its parameters' gradient (:meth:`network_gradient`)."""
        p = self.problem
        if name in p.networks:
            return self.network_gradient(name, p.network_cotangent_forms(name))
        form = p.gradient_form(name)
        n = p.control_size(name)
        if form is None:
            return np.zeros(n)
        vec = self._gradients.get(name)
        if vec is None:
            vec = self._gradients[name] = _dolfinx.create_vector(form)
        with self._assembling():
            _dolfinx.assemble_vector_into(vec, form)
        return vec.getArray(readonly=True)[:n].copy()

    def network_gradient(self, name: str, forms: dict) -> np.ndarray:
        """(n_theta,) sum_alpha <dR/dN_alpha, dN_alpha/dtheta> for network ``name``: the cotangent ``forms``
        {alpha: compiled dR/dN_alpha} assembled at the points of this rank's cells, one vector-Jacobian product
        through the network, summed over the ranks (the parameters are every rank's)."""
        network = self.problem.networks[name]
        vectors = {}
        with self._assembling():
            for alpha, form in forms.items():
                key = (name, alpha, id(form))
                vec = self._gradients.get(key)
                if vec is None:
                    vec = self._gradients[key] = _dolfinx.create_vector(form)
                _dolfinx.assemble_vector_into(vec, form)
                vectors[alpha] = vec.getArray(readonly=True)
            cotangents = network.cotangents(vectors)
        grad = np.asarray(network.parameter_vjp(network.operand_values(), cotangents), dtype=np.float64)
        return self._comm.allreduce(grad) if self._comm.size > 1 else grad

    def destroy(self) -> None:
        objs = [v for v, _ in self._base.values()]
        objs += [o for C, vin, out, _ in self._matrices.values() for o in (C, vin, out)]
        objs += list(self._gradients.values())
        for obj in objs:
            obj.destroy()
        self._base.clear()
        self._matrices.clear()
        self._scipy.clear()
        self._gradients.clear()
