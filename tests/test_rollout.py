"""Rollout (fempdl/layer/rollout.py): N steps of a step layer as one layer; per-step controls and constants,
a differentiable initial state, gradients against central differences, linear and Newton steps."""
from mpi4py import MPI
import numpy as np
import pytest
import torch

from fempdl import PRDP, KSPOptions, NewtonOptions, NonlinearSolveLayer, Rollout, SolveLayer, forms, mesh

DTS = [0.01, 0.03, 0.002, 0.05, 0.02]


@pytest.fixture(scope="module")
def lshape():
    return mesh.load("lshape", MPI.COMM_SELF, h=0.25)


def heat_step(msh, options="lu"):
    return SolveLayer(forms.heat.problem(msh, controls=("u0", "f")), options)


def nonlinear_step(msh):
    problem = forms.nonlinear_diffusion.problem(msh, controls=("u0", "f"), alpha=2.0, dt=0.01)
    return NonlinearSolveLayer(problem, NewtonOptions(rtol=1e-13, atol=1e-15, ksp="lu"))


def inputs(problem, steps, seed=0):
    g = torch.Generator().manual_seed(seed)
    n = problem.output_size
    u0 = 0.3 * torch.rand(2, n, dtype=torch.float64, generator=g)
    f = torch.rand(2, steps, problem.control_size("f"), dtype=torch.float64, generator=g)
    return u0, f


def directional_check(loss, tensors, rel=1e-7):
    """grad . d against the central difference (loss(x + h d) - loss(x - h d)) / 2h for a random d."""
    tensors = [t.detach().clone().requires_grad_() for t in tensors]
    loss(*tensors).backward()
    g = torch.Generator().manual_seed(1)
    dirs = [torch.rand(t.shape, dtype=t.dtype, generator=g) - 0.5 for t in tensors]
    exact = sum(float((t.grad * d).sum()) for t, d in zip(tensors, dirs))
    h = 1e-6
    with torch.no_grad():
        plus = float(loss(*[t + h * d for t, d in zip(tensors, dirs)]))
        minus = float(loss(*[t - h * d for t, d in zip(tensors, dirs)]))
    fd = (plus - minus) / (2 * h)
    assert abs(exact - fd) <= rel * max(abs(fd), 1e-12), (exact, fd)


@pytest.mark.parametrize("make_step", [heat_step, nonlinear_step], ids=["heat", "nonlinear"])
def test_rollout_equals_the_hand_loop_and_restores_the_constants(lshape, make_step):
    step = make_step(lshape)
    rollout = Rollout(step, "u0")
    u0, f = inputs(step.problem, len(DTS))
    dt = step.problem.constants["dt"]
    before = float(dt.value)
    with torch.no_grad():
        out = rollout(u0, len(DTS), constants={"dt": DTS}, per_step={"f": f})
        assert out.shape == (2, len(DTS) + 1, step.problem.output_size)
        assert float(dt.value) == before
        u = u0
        for k, value in enumerate(DTS):
            dt.value = value
            u = step(u0=u, f=f[:, k], initial_guess=u)
            torch.testing.assert_close(out[:, k + 1], u, rtol=1e-12, atol=1e-14)
        dt.value = before
        torch.testing.assert_close(out[:, 0], u0)
        last = rollout(u0, len(DTS), constants={"dt": DTS}, per_step={"f": f}, outputs=[-1, 2])
        torch.testing.assert_close(last, out[:, [len(DTS), 2]])
    step.close()


@pytest.mark.parametrize("make_step", [heat_step, nonlinear_step], ids=["heat", "nonlinear"])
def test_gradients_match_central_differences_with_a_varying_dt(lshape, make_step):
    step = make_step(lshape)
    rollout = Rollout(step, "u0")
    u0, f = inputs(step.problem, len(DTS))
    weights = torch.rand(2, 2, step.problem.output_size, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(2))

    def per_step_loss(u0, f):          # the initial state and a source per step, two observed states
        u = rollout(u0, len(DTS), constants={"dt": DTS}, per_step={"f": f}, outputs=[3, 5])
        return (weights * u ** 2).sum()

    def constant_loss(u0, f):          # a source constant in time, the final state
        return (weights[:, 0] * rollout(u0, len(DTS), constants={"dt": DTS}, f=f, outputs=[5])[:, 0]).sum()

    directional_check(per_step_loss, [u0, f])
    directional_check(constant_loss, [u0, f[:, 0]])
    step.close()


def test_prdp_moves_the_cap_of_every_step(lshape):
    step = heat_step(lshape, KSPOptions.preset("jacobi", max_it=3))
    rollout = Rollout(step, "u0")
    ctrl = PRDP(rollout, k0=2, k_cap=10)
    assert step.max_it == rollout.max_it == 2 and step.health is not None
    u0, f = inputs(step.problem, 4)
    rollout(u0, 4, f=f[:, 0].clone().requires_grad_()).sum().backward()
    assert step.stats.forward_solves == 2 * 4 and step.stats.max_forward_iterations == 2
    ctrl.k = 5
    ctrl.load_state_dict(ctrl.state_dict())
    assert step.max_it == 5
    step.close()


def test_bad_calls_are_named(lshape):
    step = heat_step(lshape)
    rollout = Rollout(step, "u0")
    u0, f = inputs(step.problem, 3)
    bad = [
        (dict(constants={"dt": [0.1, 0.2]}), r"one value per step, shape \(3,\)"),
        (dict(constants={"tau": [0.1] * 3}), "no Constant 'tau'"),
        (dict(constants={"dt": [0.1, np.nan, 0.1]}), "NaN"),
        (dict(u0=u0), "pass it as `initial`"),
        (dict(per_step={"f": f[:, :2]}), r"\(B, N, n_m\) or \(N, n_m\) with N = steps = 3"),
        (dict(f=f[:, 0], per_step={"f": f}), "both constant in time and per step"),
        (dict(outputs=[4]), r"state indices in 0 ... 3"),
        (dict(g=f[:, 0]), "unknown control 'g'"),
    ]
    for kwargs, message in bad:
        with pytest.raises(ValueError, match=message):
            rollout(u0, 3, **kwargs)
    with pytest.raises(ValueError, match="steps must be"):
        rollout(u0, 0)
    with pytest.raises(ValueError, match="no control 'f0'"):
        Rollout(step, "f0")
    kappa_step = SolveLayer(forms.heat.problem(lshape, controls=("u0", "kappa"), kappa_space="DG0"), "lu")
    with pytest.raises(ValueError, match="must live in the solution's space"):
        Rollout(kappa_step, "kappa")
    for lay in (step, kappa_step):
        lay.close()


SCHEDULES = ["all", ("revolve", 2), ("multistage", 1, 2)]


@pytest.mark.parametrize("make_step", [heat_step, nonlinear_step,
                                       lambda msh: heat_step(msh, KSPOptions.preset("jacobi", max_it=4))],
                         ids=["heat-lu", "nonlinear", "heat-capped-jacobi"])
def test_every_schedule_gives_the_autograd_gradient(lshape, make_step, tmp_path):
    step = make_step(lshape)
    steps = 7
    u0, f = inputs(step.problem, steps)
    dts = np.linspace(0.005, 0.04, steps)
    weights = torch.rand(2, 2, step.problem.output_size, dtype=torch.float64,
                         generator=torch.Generator().manual_seed(3))

    def run(rollout):
        x, g, c = u0.clone().requires_grad_(), f.clone().requires_grad_(), f[:, 0].clone().requires_grad_()
        u = rollout(x, steps, constants={"dt": dts}, per_step={"f": g}, outputs=[4, -1])
        (weights * u ** 2).sum().backward()
        v = rollout(x, steps, constants={"dt": dts}, f=c, outputs=[-1])
        (weights[:, 0] * v[:, 0]).sum().backward()
        return u.detach(), x.grad, g.grad, c.grad

    reference = run(Rollout(step, "u0", schedule="autograd"))
    for schedule in (None, *SCHEDULES):           # None: one node, as "all"
        rollout = Rollout(step, "u0", schedule=schedule, disk_dir=str(tmp_path))
        for got, want in zip(run(rollout), reference):
            torch.testing.assert_close(got, want, rtol=1e-12, atol=1e-14)
        stats = rollout.schedule_stats
        assert stats.steps == steps and stats.adjoint_steps == steps
        if isinstance(step, SolveLayer):     # a linear step's adjoint reads no state: none kept, none run again
            assert (stats.recomputed, stats.most_in_memory, stats.most_on_disk) == (0, 2, 0)
        elif schedule in (None, "all"):
            assert stats.recomputed == 0 and stats.most_in_memory == steps + 1
        elif schedule[0] == "revolve":
            assert stats.recomputed > 0 and stats.most_in_memory <= 2 + 2
        else:
            assert stats.recomputed > 0 and stats.most_on_disk >= 1 and stats.most_in_memory <= 1 + 2
    assert list(tmp_path.iterdir()) == []                # the disk snapshots are gone
    step.close()


def test_schedules_are_checked(lshape):
    step = heat_step(lshape)
    for bad in ("revolve", ("revolve", 0), ("multistage", 0, 0), ("multistage", -1, 2), ("binomial", 3)):
        with pytest.raises(ValueError, match="schedule|snapshot"):
            Rollout(step, "u0", schedule=bad)
    unrolled = SolveLayer(step.problem, KSPOptions.preset("jacobi", max_it=3), diff="unrolled")
    with pytest.raises(ValueError, match="runs the step's implicit adjoint"):
        Rollout(unrolled, "u0", schedule=("revolve", 2))
    for lay in (step, unrolled):
        lay.close()


@pytest.mark.parametrize("schedule", [None, "all"])
def test_a_shared_initial_state_with_batched_controls(lshape, schedule):
    """u_0 (n,) shared by a batch of sources: (B, N + 1, n), the first row of each sample u_0."""
    step = heat_step(lshape)
    u0, f = inputs(step.problem, 3)
    out = Rollout(step, "u0", schedule=schedule)(u0[0], 3, per_step={"f": f})
    assert out.shape == (2, 4, step.problem.output_size)
    assert torch.equal(out[0, 0], u0[0]) and torch.equal(out[1, 0], u0[0])


def test_memory_under_a_schedule_grows_with_its_snapshots_not_its_steps():
    """NumPy's allocations (the scheduled path's states live in NumPy; tracemalloc sees them) during
    forward + backward of a 120-step heat rollout: with a kappa gradient (its adjoint reads u_k+1)
    storing every state holds at least N n floats, revolve with 3 snapshots a small multiple of n, and
    both give the same gradient; with the source's gradient alone (an adjoint that reads no state) even
    "all" keeps no state."""
    import tracemalloc

    import dolfinx.mesh

    steps, peaks, grads = 120, {}, {}
    msh = dolfinx.mesh.create_unit_square(MPI.COMM_SELF, 40, 40)                  # 1,681 DOFs
    step = SolveLayer(forms.heat.problem(msh, controls=("u0", "f", "kappa")), "lu")
    n = step.problem.output_size
    u0, f = inputs(step.problem, 1)
    kappa = torch.ones(step.problem.control_size("kappa"), dtype=torch.float64)
    cases = (("all", "all", "kappa", steps), ("revolve", ("revolve", 3), "kappa", steps),
             ("stateless", "all", "f", steps), ("stateless, N/4", "all", "f", steps // 4))
    for name, schedule, wanted, n_steps in cases:
        rollout = Rollout(step, "u0", schedule=schedule)
        given = {"f": f[:, 0].clone(), "kappa": kappa.clone()}
        given[wanted].requires_grad_()
        rollout(u0, 2, **given, outputs=[2]).square().sum().backward()   # what a first call builds once
        given[wanted].grad = None
        tracemalloc.start()
        rollout(u0, n_steps, **given, outputs=[n_steps]).square().sum().backward()
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        grads[name] = given[wanted].grad
    state = 2 * n * 8                                        # one state of the batch of 2, in bytes
    assert peaks["all"] >= steps * state, (peaks, state)
    assert peaks["revolve"] <= 40 * state, (peaks, state)      # 3 snapshots, a step's arrays, fixed overhead
    # No state kept: the peak is a step's work arrays, the same for N/4 steps as for N ("all": N states).
    assert peaks["stateless"] <= peaks["stateless, N/4"] + 8 * state < peaks["all"] / 3, (peaks, state)
    assert torch.allclose(grads["all"], grads["revolve"], rtol=1e-12, atol=0)


@pytest.mark.parametrize("schedule", [None, ("revolve", 2)])
def test_float32_inputs_give_float32_states_and_the_float64_gradient_to_single_precision(lshape, schedule):
    """The solves run in float64 whatever the inputs; the states and gradients come back in float32."""
    step = heat_step(lshape)
    u0, f = inputs(step.problem, 4)
    results = {}
    for dtype in (torch.float64, torch.float32):
        a, b = u0.detach().to(dtype).requires_grad_(), f.detach().to(dtype).requires_grad_()
        out = Rollout(step, "u0", schedule=schedule)(a, 4, constants={"dt": DTS[:4]}, per_step={"f": b})
        out.square().sum().backward()
        assert out.dtype == a.grad.dtype == b.grad.dtype == dtype
        results[dtype] = (out.detach(), a.grad, b.grad)
    for x64, x32 in zip(results[torch.float64], results[torch.float32]):
        # float32 inputs and outputs: round-off of a few units of 2^-24 relative to the largest entry
        assert float((x64 - x32.double()).abs().max()) <= 1e-5 * float(x64.abs().max())


def test_a_rollout_without_a_schedule_is_one_node_unless_its_steps_must_be_layer_calls(lshape):
    """schedule=None runs an eager call as "all" (no layer call per step) and gives the gradient of autograd
    through every step; a hooked step and torch.func get the step's calls, with the same gradient."""
    step = nonlinear_step(lshape)
    steps = 4
    u0, f = inputs(step.problem, steps)
    rollout = Rollout(step, "u0")

    def loss(m):
        return (rollout(u0, steps, f=m, outputs=[2, -1]) ** 2).sum()

    calls = []
    m = f[:, 0].clone().requires_grad_()
    (one_node,) = torch.autograd.grad(loss(m), m)
    assert rollout.schedule_stats.steps == steps and rollout.schedule_stats.recomputed == 0
    handle = step.register_forward_pre_hook(lambda *_: calls.append(1))
    rollout.schedule_stats = None
    (hooked,) = torch.autograd.grad(loss(m), m)
    handle.remove()
    assert len(calls) == steps and rollout.schedule_stats is None
    by_func = torch.func.grad(loss)(f[:, 0].clone())
    assert rollout.schedule_stats is None
    for other in (hooked, by_func):
        torch.testing.assert_close(other, one_node, rtol=1e-12, atol=1e-14)
    step.close()


@pytest.mark.parametrize("schedule", [None, ("revolve", 2)])
def test_a_second_derivative_through_a_one_node_rollout_is_refused(lshape, schedule):
    """create_graph=True gives the first-order gradient; differentiating it again raises instead of silently
    dropping the step adjoints' second-order terms."""
    step = heat_step(lshape)
    u0, f = inputs(step.problem, 3)
    m = f[:, 0].clone().requires_grad_()
    u = Rollout(step, "u0", schedule=schedule)(u0, 3, f=m, outputs=[-1])
    (g,) = torch.autograd.grad((u ** 2).sum(), m, create_graph=True)
    with pytest.raises(RuntimeError, match="second derivatives"):
        g.sum().backward()
    step.close()


def test_an_input_changed_in_place_after_a_one_node_forward_is_refused_at_backward(lshape):
    """The one-node forward reads its float64 inputs without copying them; a change in place before the
    backward would silently give the gradient of other inputs. Autograd's version check refuses it."""
    step = nonlinear_step(lshape)
    u0, f = inputs(step.problem, 3)
    m = f[:, 0].clone().requires_grad_()
    source = m * 1.0
    u = Rollout(step, "u0")(u0, 3, f=source, outputs=[-1])
    with torch.no_grad():
        source += 1.0
    with pytest.raises(RuntimeError, match="modified by an inplace operation"):
        u.sum().backward()
    step.close()


@pytest.mark.parametrize("schedule", [None, "autograd", ("revolve", 2)])
def test_states_that_overflow_float32_are_named_as_a_step_layer_names_them(lshape, schedule):
    """float32 inputs whose states are finite in float64 but not in float32 (u ~ f / kappa ~ 1e40 at a huge
    dt): an OverflowError, not inf states, whether the steps are layer calls or one node."""
    problem = forms.heat.problem(lshape, controls=("u0", "f", "kappa"), dt=1e30)
    step = SolveLayer(problem, "lu")
    u0 = torch.zeros(problem.output_size, dtype=torch.float32)
    f = torch.full((problem.control_size("f"),), 1e10, dtype=torch.float32)
    kappa = torch.full((problem.control_size("kappa"),), 1e-30, dtype=torch.float32)
    with pytest.raises(OverflowError, match="overflows torch.float32; pass float64 controls"):
        Rollout(step, "u0", schedule=schedule)(u0, 2, f=f, kappa=kappa)
    step.close()
