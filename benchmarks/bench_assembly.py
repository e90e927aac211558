"""A Newton step's assemblies alone: the Jacobian through PETSc's insertion against DOLFINx's CSR assembly
into the arrays PETSc shares (fempdl.core.matrices), and fixed coefficients as P1 Functions against Constants.

The form: one backward-Euler step of nonlinear heat on the unit square (P1, u = 0 on the boundary),

    F(u; v) = ∫ (u - u_k) v / dt + kappa (1 + alpha u^2) ∇u·∇v - f v dx,   J = dF/du,

at a state u with values in [-1, 1], as ``forms.nonlinear_diffusion`` builds it, with kappa = alpha = 1
either fixed numbers (``"constants"``: fem.Constants, what the form makes of a number) or P1 fields
(``"fields"``: what it made of them before, and what it makes of controls). Timed, each the minimum of
``--repeats`` calls after a warm-up (``bench_common.timed``), in milliseconds:

* ``jacobian_petsc_ms``: zero a PETSc matrix, ``dolfinx.fem.petsc.assemble_matrix``, MatAssembly (what a
  hand-written DOLFINx loop does, and fempdl on more than one rank);
* ``jacobian_csr_ms``: ``fempdl.core.matrices.assemble_matrix_into`` on a CSR-backed matrix (one rank);
* ``residual_ms``: F lifted by J's boundary columns (``fempdl.core._dolfinx.assemble_residual_into``).

The two Jacobians must be equal bit for bit. Writes ``bench-results/bench_assembly_<stack>.json`` (``--out``)
with the machine and the load average at the start and the end. Run (from the repository root, on an idle
machine; either stack)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_assembly.py
    OMP_WAIT_POLICY=PASSIVE .venv-pypi/bin/python benchmarks/bench_assembly.py
"""
from __future__ import annotations

import os

os.environ["OMP_NUM_THREADS"] = "1"          # before any OpenMP runtime loads: one thread, as the rollouts run

from mpi4py import MPI


def timed_ms(fn, repeats: int) -> float:
    from bench_common import timed
    return 1e3 * timed(fn, repeats=repeats).seconds


def measure(n: int, kind: str, repeats: int) -> dict:
    import dolfinx.fem.petsc
    import dolfinx.mesh
    import numpy as np

    from fempdl import forms
    from fempdl.core import _dolfinx, matrices

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, n, n)
    controls = ("u0", "f") if kind == "constants" else ("u0", "f", "kappa", "alpha")
    p = forms.nonlinear_diffusion.problem(msh, controls=controls, alpha=1.0, dt=0.01)
    p.u.x.array[:] = np.cos(7.0 * np.arange(len(p.u.x.array)))
    x = _dolfinx.function_vector(p.u)
    petsc = dolfinx.fem.petsc.create_matrix(p.J_form)
    csr = matrices.create_matrix(p.J_form)
    b = _dolfinx.create_vector(p.F_form)

    def jacobian_petsc():
        petsc.zeroEntries()
        _dolfinx.assemble_petsc_matrix(petsc, p.J_form, p.bcs)
        petsc.assemble()

    row = {"dofs": p.output_size, "coefficients": kind,
           "jacobian_petsc_ms": timed_ms(jacobian_petsc, repeats),
           "jacobian_csr_ms": timed_ms(lambda: matrices.assemble_matrix_into(csr, p.J_form, p.bcs), repeats),
           "residual_ms": timed_ms(lambda: _dolfinx.assemble_residual_into(b, p.F_form, p.J_form, p.bcs, x), repeats)}
    if any(not np.array_equal(a, c) for a, c in zip(petsc.getValuesCSR(), csr.getValuesCSR())):
        raise SystemExit(f"the CSR-assembled Jacobian differs from PETSc's at n = {n}, {kind}")
    row["csr_over_petsc"] = row["jacobian_csr_ms"] / row["jacobian_petsc_ms"]
    return row


def main() -> None:
    from fempdl.core import _dolfinx

    import bench_common
    parser = bench_common.parser(__file__, __doc__.splitlines()[0], repeats=50, quick="n = 32 and 96", quick_repeats=10,
                                 out_suffix=f"_{_dolfinx.STACK}")
    parser.add_argument("--n", type=int, nargs="+", default=None, help="cells per side (default 32 96 256)")
    args = parser.parse_args()
    args.n = args.n or ([32, 96] if args.quick else [32, 96, 256])
    with bench_common.report(__file__, args.out, repeats=args.repeats) as data:
        data["rows"] = measure_all(args)


def measure_all(args) -> list:
    rows = [measure(n, kind, args.repeats) for n in args.n for kind in ("fields", "constants")]
    for row in rows:
        print({k: round(v, 3) if isinstance(v, float) else v for k, v in row.items()}, flush=True)
    fields = {r["dofs"]: r for r in rows if r["coefficients"] == "fields"}
    for r in rows:
        if r["coefficients"] == "constants":
            base = fields[r["dofs"]]
            r["jacobian_constants_over_fields"] = r["jacobian_petsc_ms"] / base["jacobian_petsc_ms"]
            r["residual_constants_over_fields"] = r["residual_ms"] / base["residual_ms"]
            # Today's fempdl against its own path before: CSR + Constants over PETSc insertion + fields.
            r["jacobian_now_over_before"] = r["jacobian_csr_ms"] / base["jacobian_petsc_ms"]
    return rows


if __name__ == "__main__":
    main()
