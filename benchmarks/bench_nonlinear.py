"""Per-sample forward + backward of a NonlinearSolveLayer against plain DOLFINx Newton and a hand adjoint.

Two problems, each with one control and the loss J = sum(u * W) (W standard normal):

* ``poisson``: -div((1 + u^2) grad u) = f on the unit square (P1, u = 0 on the
  boundary), control f (P1);
* ``hyperelastic``: a compressible neo-Hookean box [0, 1] x [0, 0.2]^2 (P1
  vectors) clamped at x = 0 and pulled by a traction T (a P1 vector control) on x = 1.

Per sample, both sides run the same mathematics:

* fempdl: ``NonlinearSolveLayer(problem, NewtonOptions(snes_type=..., ksp="lu"))``,
  forward from zero and the implicit backward (J(u)^T lam = dJ/du by LU, then the
  assembled gradient form), as ``loss.backward()`` runs it;
* baseline: DOLFINx's own Newton (0.5.2: ``fem.petsc.NonlinearProblem`` and
  ``nls.petsc.NewtonSolver``; 0.11: the SNES-based ``fem.petsc.NonlinearProblem``)
  to the same tolerances with MUMPS LU per step, then an adjoint written by hand
  with dolfinx and petsc4py: J assembled at u, a transposed MUMPS solve, the form
  -d/dm F(u, lam) assembled.

Both sides' solutions and gradients are compared (max relative difference) and
their Newton steps recorded. Timing: each is warmed up once, then the two are
interleaved ``--repeats`` times (``bench_common.interleaved``); the figure is the ratio of the minima (other
processes only add time). Target: fempdl / baseline <= 1.15. Each row also holds
the medians of the parts (``median_parts_s``): both sides' Newton solves and
adjoints, and fempdl's layer around them (torch operator, checks, conversions);
``layer_alone_min_s`` is that layer with the solves replaced by stored results. Writes
``bench-results/bench_nonlinear_<stack>.json`` (``--out``) through ``bench_common.report``; ``--quick``
runs the small sizes, 3 repeats.

Run (from the repository root)::

    OMP_WAIT_POLICY=PASSIVE .venv/bin/python benchmarks/bench_nonlinear.py
    OMP_WAIT_POLICY=PASSIVE .venv-pypi/bin/python benchmarks/bench_nonlinear.py
"""
from __future__ import annotations

import sys
import time

from mpi4py import MPI
import dolfinx.fem
import dolfinx.fem.petsc
import dolfinx.mesh
import numpy as np
import torch
import ufl
from petsc4py import PETSc

from fempdl import NewtonOptions, NonlinearProblem, NonlinearSolveLayer
from fempdl.core import _dolfinx

import bench_common
from bench_common import interleaved, reduce, timed

TARGET = 1.15
RTOL, ATOL = 1e-10, 1e-12
SIZES = {"poisson": {"small": 32, "large": 96}, "hyperelastic": {"small": 4, "large": 8}}
MUMPS = {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}


def poisson(n: int):
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    V = _dolfinx.function_space(msh, "Lagrange", 1)
    u, v, f = dolfinx.fem.Function(V), ufl.TestFunction(V), dolfinx.fem.Function(V)
    F = (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) * ufl.dx - f * v * ufl.dx
    bc = _dolfinx.dirichlet_bc(V, 0.0, _dolfinx.boundary_facets(msh))
    control = np.full(V.dofmap.index_map.size_local, 8.0)
    return F, u, [bc], f, control


def hyperelastic(n: int):
    msh = dolfinx.mesh.create_box(MPI.COMM_WORLD, [[0, 0, 0], [1, 0.2, 0.2]], [5 * n, n, n])
    V = _dolfinx.function_space(msh, "Lagrange", 1, shape=(3,))
    u, v, T = dolfinx.fem.Function(V), ufl.TestFunction(V), dolfinx.fem.Function(V)
    E, nu = 10.0, 0.3
    mu, lmbda = E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))
    Fd = ufl.Identity(3) + ufl.grad(u)
    Jd = ufl.det(Fd)
    P = mu * (Fd - ufl.inv(Fd).T) + lmbda * ufl.ln(Jd) * ufl.inv(Fd).T
    fdim = msh.topology.dim - 1
    right = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 1.0))
    tags = dolfinx.mesh.meshtags(msh, fdim, right, np.ones(len(right), dtype=np.int32))
    ds = ufl.Measure("ds", domain=msh, subdomain_data=tags)
    F = ufl.inner(P, ufl.grad(v)) * ufl.dx - ufl.inner(T, v) * ds(1)
    left = dolfinx.mesh.locate_entities_boundary(msh, fdim, lambda x: np.isclose(x[0], 0.0))
    bc = _dolfinx.dirichlet_bc(V, dolfinx.fem.Function(V), left)      # clamped
    control = np.zeros(V.dofmap.index_map.size_local * 3)
    control[2::3] = -0.02                      # a downward pull on the free end: a tip deflection of about 0.2
    return F, u, [bc], T, control


class DolfinxNewton:
    """DOLFINx's Newton on (F, u, bcs) with MUMPS LU per step, and a hand-written adjoint for control m."""

    def __init__(self, F, u, bcs, m):
        self.u, self.bcs, self.m = u, bcs, m
        V = u.function_space
        self.J = ufl.derivative(F, u, ufl.TrialFunction(V))
        if hasattr(dolfinx.fem.petsc, "NewtonSolverNonlinearProblem"):       # 0.10+: SNES
            self.problem = dolfinx.fem.petsc.NonlinearProblem(
                F, u, bcs=bcs, J=self.J, petsc_options_prefix="bench_nl_",
                petsc_options={"snes_type": "newtonls", "snes_linesearch_type": "basic", "snes_rtol": RTOL,
                               "snes_atol": ATOL, "snes_stol": 0.0, "snes_max_it": 50, **MUMPS})
            self.newton = None
        else:
            from dolfinx.nls.petsc import NewtonSolver
            self.problem = dolfinx.fem.petsc.NonlinearProblem(F, u, bcs=bcs, J=self.J)
            self.newton = NewtonSolver(MPI.COMM_WORLD, self.problem)
            self.newton.convergence_criterion = "residual"
            self.newton.rtol, self.newton.atol, self.newton.max_it = RTOL, ATOL, 50
            ksp = self.newton.krylov_solver
            ksp.setType("preonly")
            ksp.getPC().setType("lu")
            ksp.getPC().setFactorSolverType("mumps")
        # The adjoint, by hand: J at u, transposed LU, the gradient form -d/dm F(u, lam).
        self.lam = dolfinx.fem.Function(V)
        self.J_form = dolfinx.fem.form(self.J)
        self.A = dolfinx.fem.petsc.create_matrix(self.J_form)
        self.ksp = PETSc.KSP().create(MPI.COMM_WORLD)
        self.ksp.setOperators(self.A)
        self.ksp.setType("preonly")
        self.ksp.getPC().setType("lu")
        self.ksp.getPC().setFactorSolverType("mumps")
        test = F.arguments()[0]
        dm = ufl.TestFunction(m.function_space)
        self.grad_form = dolfinx.fem.form(ufl.derivative(-ufl.replace(F, {test: self.lam}), m, dm))
        self.grad_vec = _dolfinx.create_vector(self.grad_form)
        self.g, self.x = self.A.createVecs()
        self.bc_dofs = _dolfinx.bc_dofs_owned(bcs, V.dofmap.index_map.size_local * V.dofmap.index_map_bs)
        self.steps = 0

    def forward_backward(self, control: np.ndarray, W: np.ndarray):
        n_m = len(control)
        self.m.x.array[:n_m] = control
        self.m.x.scatter_forward()
        self.u.x.array[:] = 0.0
        t0 = time.perf_counter()
        if self.newton is None:
            self.problem.solve()
            self.steps = self.problem.solver.getIterationNumber()
        else:
            self.steps, _ = self.newton.solve(self.u)
        self.newton_time = time.perf_counter() - t0
        n = len(W)
        state = self.u.x.array[:n].copy()
        self.A.zeroEntries()
        dolfinx.fem.petsc.assemble_matrix(self.A, self.J_form, self.bcs)
        self.A.assemble()
        g = W.copy()
        g[self.bc_dofs] = 0.0
        self.g.setArray(g)
        self.ksp.solveTranspose(self.g, self.x)
        self.lam.x.array[:n] = self.x.getArray(readonly=True)
        self.lam.x.scatter_forward()
        _dolfinx.assemble_vector_into(self.grad_vec, self.grad_form)
        return state, self.grad_vec.getArray(readonly=True)[:n_m].copy()


class PartTimer:
    """Times a NonlinearSystem's ``solve`` (the Newton solves) and ``adjoint`` inside the layer's calls:
    the rest of a forward + backward is the layer's torch operator, its checks and conversions."""

    def __init__(self, system):
        self.last = {}
        for part in ("solve", "adjoint"):
            setattr(system, part, self._timed(part, getattr(system, part)))

    def _timed(self, part, method):
        def call(*args, **kwargs):
            t0 = time.perf_counter()
            result = method(*args, **kwargs)
            self.last[part] = time.perf_counter() - t0
            return result
        return call


def layer_alone(layer, name: str, control: np.ndarray, W: np.ndarray, repeats: int) -> float:
    """The layer's forward + backward with its system's solve and adjoint replaced by their stored
    results: the torch side alone, on warm caches (the minimum over ``10 * repeats`` calls)."""
    system = layer.system
    controls = {name: control[None, :]}
    U = system.solve(controls, 1)
    grads = system.adjoint(controls, U, W[None, :], [name])
    system.solve = lambda *args, **kwargs: U.copy()
    system.adjoint = lambda *args, **kwargs: {k: v.copy() for k, v in grads.items()}
    return timed(lambda: fempdl_forward_backward(layer, name, control, W), repeats=10 * repeats, warmup=0).seconds


def fempdl_forward_backward(layer, name: str, control: np.ndarray, W: np.ndarray):
    m = torch.tensor(control, dtype=torch.float64, requires_grad=True)
    u = layer(**{name: m})
    (u * torch.from_numpy(W)).sum().backward()
    return u.detach().numpy(), m.grad.numpy()


def bench_case(case: str, size: str, snes_type: str, repeats: int, rng) -> dict:
    build = {"poisson": poisson, "hyperelastic": hyperelastic}[case]
    F, u, bcs, m, control = build(SIZES[case][size])
    name = "f" if case == "poisson" else "T"
    problem = NonlinearProblem(F, u, bcs, {name: m})
    layer = NonlinearSolveLayer(problem, NewtonOptions(snes_type=snes_type, rtol=RTOL, atol=ATOL, ksp="lu"))
    W = rng.standard_normal(problem.output_size)
    # The baseline on its own unknown (same space, same DOF order): the layer's u is its work state.
    u_base, m_base = dolfinx.fem.Function(u.function_space), dolfinx.fem.Function(m.function_space)
    Fb = ufl.replace(F, {u: u_base, m: m_base})
    baseline = DolfinxNewton(Fb, u_base, bcs, m_base)
    parts = PartTimer(layer.system)
    ours = fempdl_forward_backward(layer, name, control, W)       # warm-up: JIT, symbolic factorisation
    theirs = baseline.forward_backward(control, W)
    split = {"fempdl_newton": [], "fempdl_adjoint": [], "fempdl_layer": [], "dolfinx_newton": [],
             "dolfinx_adjoint": []}
    results = {}

    def run_fempdl() -> float:
        t0 = time.perf_counter()
        results["fempdl"] = fempdl_forward_backward(layer, name, control, W)
        seconds = time.perf_counter() - t0
        split["fempdl_newton"].append(parts.last["solve"])
        split["fempdl_adjoint"].append(parts.last["adjoint"])
        split["fempdl_layer"].append(seconds - parts.last["solve"] - parts.last["adjoint"])
        return seconds

    def run_dolfinx() -> float:
        t0 = time.perf_counter()
        results["dolfinx"] = baseline.forward_backward(control, W)
        seconds = time.perf_counter() - t0
        split["dolfinx_newton"].append(baseline.newton_time)
        split["dolfinx_adjoint"].append(seconds - baseline.newton_time)
        return seconds

    timings = interleaved({"fempdl": run_fempdl, "dolfinx": run_dolfinx}, repeats=repeats, warmup=0)
    ours, theirs = results["fempdl"], results["dolfinx"]

    def rel(a, b):
        return float(np.abs(a - b).max() / max(np.abs(b).max(), 1e-300))
    row = {
        "case": case, "size": size, "snes_type": snes_type, "dofs": problem.output_size,
        "control_dofs": problem.control_size(name),
        "newton_steps": {"fempdl": layer.stats.last_newton.steps, "dolfinx": int(baseline.steps)},
        "max_rel_diff": {"solution": rel(ours[0], theirs[0]), "gradient": rel(ours[1], theirs[1])},
        "times_s": {k: list(t.samples) for k, t in timings.items()},
        "min_s": {k: t.seconds for k, t in timings.items()},
        # Where the difference lies: medians of each part over the repeats (the Newton solves, the
        # adjoint with its gradient assembly, and for fempdl the torch layer around them).
        "median_parts_s": {k: reduce(v, "median") for k, v in split.items()},
    }
    row["ratio"] = row["min_s"]["fempdl"] / row["min_s"]["dolfinx"]
    row["layer_alone_min_s"] = layer_alone(layer, name, control, W, repeats)
    layer.close()
    return row


def main() -> int:
    parser = bench_common.parser(__file__, __doc__.split("\n")[0], repeats=7, out_suffix=f"_{_dolfinx.STACK}",
                                 quick="the small sizes", quick_repeats=3)
    parser.add_argument("--sizes", default=None, help="small,large (default both)")
    parser.add_argument("--cases", default="poisson,hyperelastic")
    parser.add_argument("--snes", default="newton", help="fempdl's SNES types, comma-separated (the baseline runs "
                        "plain Newton; 'newtonls' adds backtracking, which takes more steps on the bent box)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    args.sizes = args.sizes or ("small" if args.quick else "small,large")
    out = args.out
    rng = np.random.default_rng(args.seed)
    started = time.perf_counter()
    with bench_common.report(__file__, out, repeats=args.repeats, target_ratio_max=TARGET, results=[],
                             settings={"rtol": RTOL, "atol": ATOL, "inner": "MUMPS LU both sides",
                                       "loss": "sum(u * W), W standard normal"}) as report:
        run_all(args, rng, report)
        report["duration_s"] = time.perf_counter() - started
    print(f"ratio = fempdl / DOLFINx Newton + hand adjoint, minima over {args.repeats} interleaved repeats "
          f"(target <= {TARGET}); wrote {out}")
    return 0


def run_all(args, rng, report: dict) -> None:
    print(f"{'case':13s} {'size':6s} {'snes':9s} {'dofs':>7s} {'steps':>9s} {'fempdl s':>9s} {'dolfinx s':>9s} "
          f"{'ratio':>6s} {'du':>8s} {'dm':>8s}")
    for case in args.cases.split(","):
        for size in args.sizes.split(","):
            for snes_type in args.snes.split(","):
                row = bench_case(case, size, snes_type, args.repeats, rng)
                report["results"].append(row)
                steps = row["newton_steps"]
                print(f"{case:13s} {size:6s} {snes_type:9s} {row['dofs']:7d} "
                      f"{steps['fempdl']:4d}/{steps['dolfinx']:<4d} "
                      f"{row['min_s']['fempdl']:9.4f} {row['min_s']['dolfinx']:9.4f} {row['ratio']:6.3f} "
                      f"{row['max_rel_diff']['solution']:8.1e} {row['max_rel_diff']['gradient']:8.1e}", flush=True)


if __name__ == "__main__":
    sys.exit(main())
