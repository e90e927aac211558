"""The sides bench_rollout.py compares, each run in its own process: the problem and how one side is timed.

:func:`setup` and :func:`residual` are the heat rollout every side solves; ``side_*`` build a side's
forward alone and forward + gradient; :func:`time_side` warms them up and times them; :data:`SIDES`
names them for ``bench_rollout.py --side``. The FE stack is imported inside the functions, so the
driver can import this module without it.
"""
from __future__ import annotations

import resource
import sys

from mpi4py import MPI  # the PyPI stack needs MPI loaded before dolfinx

RTOL, ATOL, DT = 1e-10, 1e-12, 0.01
SNES = {"snes_type": "newtonls", "snes_linesearch_type": "basic", "snes_rtol": RTOL, "snes_atol": ATOL,
        "snes_stol": 0.0, "snes_max_it": 50, "ksp_type": "preonly", "pc_type": "lu",
        "pc_factor_mat_solver_type": "mumps"}


# ------------------------------------------------------------------ the problem, shared by the sides
def setup(n: int):
    import dolfinx.mesh
    import numpy as np

    from fempdl.core import _dolfinx

    msh = dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, n, n)
    V = _dolfinx.function_space(msh, "Lagrange", 1)          # either stack's spelling
    x = V.tabulate_dof_coordinates()
    u0 = 2 * np.sin(np.pi * x[:, 0]) * np.sin(np.pi * x[:, 1])
    f = 4 + 2 * np.cos(3 * x[:, 0]) * x[:, 1]
    facets = dolfinx.mesh.locate_entities_boundary(msh, 1, lambda p: np.full(p.shape[1], True))
    bc_dofs = dolfinx.fem.locate_dofs_topological(V, 1, facets)
    return msh, V, u0, f, bc_dofs


def residual(u, u_prev, f, dt):
    import ufl

    v = ufl.TestFunction(u.function_space)
    return ((u - u_prev) / dt * v + (1 + u ** 2) * ufl.inner(ufl.grad(u), ufl.grad(v)) - f * v) * ufl.dx


# ------------------------------------------------------------------ the four sides
# Each side builds ``forward(steps) -> J`` (the forward rollout and the loss alone) and ``gradient(steps) ->
# (J, dJ/df)`` (forward and gradient) and hands them to ``timed``.
def side_fempdl(args, ksp: str = "lu"):
    import dolfinx.fem
    import dolfinx.fem.petsc
    import numpy as np
    import scipy.sparse
    import torch
    import ufl

    from fempdl import NewtonOptions, NonlinearSolveLayer, Rollout, forms

    msh, V, u0, f, _ = setup(args.n)
    problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=1.0, dt=DT)
    step = NonlinearSolveLayer(problem, NewtonOptions(rtol=RTOL, atol=ATOL, snes_type="newtonls",
                                                      linesearch="basic", ksp=ksp))
    assert problem.V.dofmap.index_map.size_local == len(u0)
    rollout = Rollout(step, "u0", schedule=args.schedule)
    M = dolfinx.fem.petsc.assemble_matrix(dolfinx.fem.form(
        ufl.TrialFunction(V) * ufl.TestFunction(V) * ufl.dx))
    M.assemble()
    indptr, indices, values = M.getValuesCSR()
    csr = scipy.sparse.csr_matrix((values, indices, indptr), shape=M.getSize()).tocoo()
    mass = torch.sparse_coo_tensor(np.vstack([csr.row, csr.col]), csr.data, csr.shape).coalesce()
    initial = torch.tensor(u0)

    def loss_of(source, steps):
        uN = rollout(initial, steps, f=source, outputs=[steps])[-1]
        return uN @ torch.sparse.mm(mass, uN[:, None])[:, 0]

    def forward(steps):
        with torch.no_grad():          # no graph: what a rollout costs when only its states are wanted
            return float(loss_of(torch.tensor(f), steps))

    def gradient(steps):
        source = torch.tensor(f, requires_grad=True)
        loss = loss_of(source, steps)
        loss.backward()
        return float(loss), source.grad.numpy().copy()

    stats = step.system.stats

    def counters():
        return {"newton_steps": getattr(stats, "newton_steps", 0),
                "preconditioner_refreshes": getattr(stats, "preconditioner_refreshes", 0),
                "inner_iterations": stats.forward_iterations + stats.backward_iterations}

    return time_side(forward, gradient, args, counters)


def side_hand(args):
    import dolfinx.fem
    import dolfinx.fem.petsc
    import numpy as np
    import ufl
    from petsc4py import PETSc

    msh, V, u0, f_values, bc_dofs = setup(args.n)
    u, u_prev, f = (dolfinx.fem.Function(V) for _ in range(3))
    f.x.array[:] = f_values
    dt = dolfinx.fem.Constant(msh, DT)
    F = residual(u, u_prev, f, dt)
    bc = dolfinx.fem.dirichletbc(0.0, bc_dofs, V)
    problem = dolfinx.fem.petsc.NonlinearProblem(F, u, bcs=[bc], petsc_options_prefix="hand_",
                                                 petsc_options=dict(SNES))
    # The reverse loop: J(u_k+1)^T lam = g, dJ/df += -dF/df^T lam, g_k = -dF/du_k^T lam.
    lam = dolfinx.fem.Function(V)
    test = F.arguments()[0]
    adjoint_F = ufl.replace(F, {test: lam})
    J_form = dolfinx.fem.form(ufl.derivative(F, u))
    grad_f = dolfinx.fem.form(-ufl.derivative(adjoint_F, f, ufl.TestFunction(V)))
    grad_prev = dolfinx.fem.form(-ufl.derivative(adjoint_F, u_prev, ufl.TestFunction(V)))
    A = dolfinx.fem.petsc.create_matrix(J_form)
    ksp = PETSc.KSP().create(msh.comm)
    ksp.setOperators(A)
    ksp.setType("preonly")
    ksp.getPC().setType("lu")
    ksp.getPC().setFactorSolverType("mumps")
    rhs, sol = A.createVecs()
    vec_f, vec_prev = dolfinx.fem.petsc.create_vector(V), dolfinx.fem.petsc.create_vector(V)
    mass = dolfinx.fem.form(u * u * ufl.dx)
    dmass = dolfinx.fem.form(ufl.derivative(u * u * ufl.dx, u, ufl.TestFunction(V)))
    n = len(u0)
    newton = [0]

    def assembled(vec, form):
        with vec.localForm() as local:
            local.set(0.0)
        dolfinx.fem.petsc.assemble_vector(vec, form)
        vec.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return vec.getArray(readonly=True)[:n].copy()

    def states_and_loss(steps):
        u.x.array[:n] = u0
        u.x.scatter_forward()
        states = [u.x.array.copy()]
        for _ in range(steps):
            u_prev.x.array[:] = states[-1]
            problem.solve()
            newton[0] += problem.solver.getIterationNumber()
            states.append(u.x.array.copy())
        return states, msh.comm.allreduce(dolfinx.fem.assemble_scalar(mass))

    def forward(steps):
        return states_and_loss(steps)[1]       # the states are kept, as the reverse loop would need them

    def gradient(steps):
        states, loss = states_and_loss(steps)
        g = assembled(vec_prev, dmass)
        grad = np.zeros(n)
        for k in range(steps - 1, -1, -1):
            u.x.array[:] = states[k + 1]
            u_prev.x.array[:] = states[k]
            A.zeroEntries()
            dolfinx.fem.petsc.assemble_matrix(A, J_form, [bc])
            A.assemble()
            g[bc_dofs[bc_dofs < n]] = 0.0
            rhs.setArray(g)
            ksp.solveTranspose(rhs, sol)
            lam.x.array[:n] = sol.getArray(readonly=True)
            lam.x.scatter_forward()
            grad += assembled(vec_f, grad_f)
            g = assembled(vec_prev, grad_prev)
        return loss, grad

    return time_side(forward, gradient, args, lambda: {"newton_steps": newton[0]})


def side_dolfinx_adjoint(args):
    sys.path.insert(0, args.dxa_path)
    import dolfinx_adjoint as dxa
    import pyadjoint
    import ufl

    msh, V, u0, f_values, bc_dofs = setup(args.n)
    n = len(u0)
    tape = pyadjoint.get_working_tape()
    newton = [0]

    def annotated_loss(steps):
        """The loop and J on a fresh tape; returns J and the control f."""
        tape.clear_tape()
        f = dxa.Function(V)
        f.x.array[:n] = f_values
        f.x.scatter_forward()
        u, u_prev = dxa.Function(V), dxa.Function(V)
        with pyadjoint.stop_annotating():
            u_prev.x.array[:n] = u0
            u_prev.x.scatter_forward()
            u.x.array[:] = u_prev.x.array
        dt = dxa.Constant(msh, DT)
        F = residual(u, u_prev, f, dt)
        bc = dxa.dirichletbc(dxa.Function(V), bc_dofs)
        problem = dxa.NonlinearProblem(F, u, bcs=[bc], petsc_options=dict(SNES),
                                       adjoint_petsc_options={"ksp_type": "preonly", "pc_type": "lu",
                                                              "pc_factor_mat_solver_type": "mumps"})
        for _ in range(steps):
            problem.solve()
            newton[0] += problem.solver.getIterationNumber()
            dxa.assign(u, u_prev)
        # The problem and states live on until derivative(), as in a user's loop: the tape's adjoint blocks
        # reuse the problem's solvers (with them collected, each block builds its own: 5x the time at 1k DOFs).
        return dxa.assemble_scalar(u * u * ufl.dx), f, (problem, u, u_prev, F, bc, dt)

    def forward(steps):
        # Annotated as a gradient run would be: the forward a dolfinx-adjoint user pays before derivative().
        return float(annotated_loss(steps)[0])

    def gradient(steps):
        J, f, alive = annotated_loss(steps)
        grad = pyadjoint.ReducedFunctional(J, pyadjoint.Control(f)).derivative()
        del alive
        return float(J), grad.x.array[:n].copy()

    return time_side(forward, gradient, args, lambda: {"newton_steps": newton[0]})


def time_side(forward, gradient, args, counters) -> dict:
    """Warm-up runs of ``args.warmup_steps`` steps, then the minimum over ``args.inner_repeats`` of the forward
    alone and of forward + gradient, alternated (``bench_common.interleaved``: a change in the machine's load
    hits both times alike); ``counters()`` (name -> a cumulative count) is read around the first run of each,
    so the counts are those of one run."""
    from bench_common import interleaved

    forward(args.warmup_steps)
    gradient(args.warmup_steps)
    first: dict = {}

    def run_forward() -> None:
        before = counters()
        loss = forward(args.steps)
        first.setdefault("forward", (before, counters(), loss))

    def run_gradient() -> None:
        before = counters()
        loss, grad = gradient(args.steps)
        first.setdefault("gradient", (before, counters(), loss, grad))

    timings = interleaved({"forward": run_forward, "gradient": run_gradient}, repeats=args.inner_repeats, warmup=0)
    (before, middle, forward_loss), (_, after, loss, grad) = first["forward"], first["gradient"]
    counts = {name: after[name] - middle[name] for name in after}
    counts["forward_newton_steps"] = middle["newton_steps"] - before["newton_steps"]
    return {"forward_s": timings["forward"].seconds, "forward_gradient_s": timings["gradient"].seconds,
            "loss": loss, "forward_loss": forward_loss, "grad": grad.tolist(), **counts,
            "repeats": args.inner_repeats,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


SIDES = {"fempdl": side_fempdl, "fempdl-lagged": lambda args: side_fempdl(args, "lu-lagged"), "hand": side_hand,
         "dolfinx-adjoint": side_dolfinx_adjoint}
