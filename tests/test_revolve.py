"""BinomialRevolve (fempdl/layer/revolve.py): the action stream is one a rollout can run (every state read
exists, every reversed step has its pair (u_k, u_k+1), at most s snapshots), it runs as many steps as
checkpoint_schedules' optimal Revolve and a brute-force minimum, it is made lazily (N = 10^9 costs
nothing up front), and a Rollout under it gives the autograd gradient with the predicted recomputation."""
import functools
import itertools
import tracemalloc

from mpi4py import MPI
import checkpoint_schedules as cs
import numpy as np
import pytest
import torch

from fempdl import Rollout, SolveLayer, forms, mesh
from fempdl.layer.revolve import BinomialRevolve, recomputed_steps


def simulate(schedule, steps: int, snapshots: int) -> dict:
    """Runs the action stream on step indices (O(actions), not O(steps)) and checks it as
    CheckpointedRollout would run it; returns the steps of the first sweep, those run again, the most
    snapshots and the most adjoint dependencies held at once."""
    work, ram, deps = 0, set(), set()
    adjoint_at, first = steps, True
    counts = {"first": 0, "again": 0, "snapshots": 0, "deps": 0}
    for action in schedule:
        if isinstance(action, cs.Forward):
            assert action.n0 == work < action.n1 <= steps, (action, work)
            if action.write_ics:
                assert action.storage == cs.StorageType.RAM and action.n0 not in ram, action
                ram.add(action.n0)
            if action.write_adj_deps:
                deps.update(range(action.n0, action.n1))
            counts["first" if first else "again"] += action.n1 - action.n0
            work = action.n1
        elif isinstance(action, cs.EndForward):
            assert first and work == steps, action
            first = False
        elif isinstance(action, cs.Reverse):
            assert not first and action.n1 == adjoint_at and action.n0 < action.n1, (action, adjoint_at)
            for k in range(action.n1 - 1, action.n0 - 1, -1):
                assert k in deps, (action, k)                 # (u_k, u_k+1) kept by a Forward
                if action.clear_adj_deps:
                    deps.remove(k)
            adjoint_at = action.n0
        elif isinstance(action, (cs.Copy, cs.Move)):
            assert action.from_storage == cs.StorageType.RAM and action.to_storage == cs.StorageType.WORK
            assert action.n in ram, (action, ram)
            if isinstance(action, cs.Move):
                ram.remove(action.n)
            work = action.n
        elif isinstance(action, cs.EndReverse):
            assert adjoint_at == 0 and not ram and not deps, (adjoint_at, ram, deps)
            return counts
        else:
            raise AssertionError(f"unexpected action {action!r}")
        counts["snapshots"] = max(counts["snapshots"], len(ram))
        counts["deps"] = max(counts["deps"], len(deps))
        assert len(ram) <= snapshots, (action, ram)
    raise AssertionError("the stream ended without EndReverse")


@functools.cache
def fewest_forward_steps(m: int, k: int) -> int:
    """Brute force over every first split: the fewest forward runs besides the m that keep a step's
    adjoint dependencies, reversing m steps with k snapshots (the starting state's included)."""
    if m == 1:
        return 0
    if k == 1:
        return m * (m - 1) // 2
    return min(j + fewest_forward_steps(j, k) + fewest_forward_steps(m - j, k - 1) for j in range(1, m))


CASES = [(n, s) for n in range(2, 81) for s in range(1, 13) if s < n]


def test_steps_run_again_equal_checkpoint_schedules_revolve_and_the_brute_force_minimum():
    """For every N <= 80 and s < N, s <= 12: the same steps run again as checkpoint_schedules' Revolve (H-Revolve,
    optimal), as the brute-force minimum, and as the closed form r N - binom(s + r, s + 1); every snapshot in use."""
    for steps, s in CASES:
        ours = simulate(BinomialRevolve(steps, s), steps, s)
        theirs = simulate(cs.Revolve(steps, s), steps, s)
        assert ours["first"] == theirs["first"] == steps, (steps, s)
        assert ours["again"] == theirs["again"] == fewest_forward_steps(steps, s) == recomputed_steps(steps, s), \
            (steps, s, ours, theirs)
        assert ours["snapshots"] == s and ours["deps"] == 1, (steps, s, ours)


@pytest.mark.parametrize("steps, s", [(1000, 1), (4321, 3), (10_000, 10), (100_000, 100), (77_777, 7)])
def test_long_streams_are_valid_and_run_the_closed_form(steps, s):
    """Beyond where checkpoint_schedules' Revolve builds in a test's time: the closed form (checked above against
    it and the brute force) and a valid stream using all s snapshots."""
    counts = simulate(BinomialRevolve(steps, s), steps, s)
    assert counts["first"] == steps and counts["again"] == recomputed_steps(steps, s), counts
    assert counts["snapshots"] == s and counts["deps"] == 1


def test_closed_form_at_known_points():
    """s = 1 runs u_0 ... u_k+1 again to reverse each step k < N - 1 (1 + ... + N - 1 steps); N = 10, s = 3 is
    beta(3, 2), where every step runs forward twice besides its taped run; a demonstration's 5,000 steps with
    100 snapshots ran 9,898 again (bench-results/demo_rollout_memory.json)."""
    assert recomputed_steps(12, 1) == 66
    assert recomputed_steps(10, 3) == 15                     # beta(3, 2) = 10: 2 * 10 - beta(4, 1)
    assert recomputed_steps(5000, 100) == 9898
    assert recomputed_steps(5, 5) == recomputed_steps(5, 50) == 0


@pytest.mark.parametrize("steps", [1, 2, 7, 40])
def test_enough_snapshots_keep_every_state(steps):
    """s >= N: the first sweep keeps every pair and no step runs twice."""
    for s in (steps, steps + 1, 10 * steps):
        counts = simulate(BinomialRevolve(steps, s), steps, s)
        assert counts == {"first": steps, "again": 0, "snapshots": 0, "deps": steps}, (steps, s, counts)


def test_a_billion_steps_cost_nothing_up_front():
    """Made as iterated: building for N = 10^9 and taking the whole first sweep (at most s + 1 Forward actions,
    s snapshots at split points) and the first reversals allocates a few kB, where checkpoint_schedules'
    Revolve would hold its whole schedule."""
    steps, s = 10**9, 100
    tracemalloc.start()
    try:
        schedule = BinomialRevolve(steps, s)
        first = list(itertools.islice(schedule, 2 * s + 10))
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 2 * 2**20, peak
    end = next(i for i, a in enumerate(first) if isinstance(a, cs.EndForward))
    sweep = first[:end]
    assert len(sweep) <= s + 1 and all(isinstance(a, cs.Forward) for a in sweep)
    assert sweep[0].n0 == 0 and sweep[-1].n1 == steps and sweep[-1].write_adj_deps
    assert all(a.n1 == b.n0 for a, b in zip(sweep, sweep[1:]))
    assert sum(a.write_ics for a in sweep) == s
    reverse = first[end + 1]
    assert isinstance(reverse, cs.Reverse) and reverse.args == (steps, steps - 1, True), reverse
    assert schedule.max_n == steps and not schedule.is_exhausted


def test_bad_arguments_are_named():
    for bad in (0, -1, 2.0, True, None):
        with pytest.raises(ValueError, match=r"snapshots must be an int >= 1"):
            BinomialRevolve(10, bad)
        with pytest.raises(ValueError, match=r"steps must be an int >= 1"):
            BinomialRevolve(bad, 3)


@pytest.fixture(scope="module")
def heat():
    # kappa: its gradient reads the states (a heat step's u0 and f gradients alone would keep none)
    step = SolveLayer(forms.heat.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.25), controls=("u0", "f", "kappa")),
                      "lu")
    yield step
    step.close()


def test_rollout_gradient_equals_autograd_and_recomputes_as_predicted(heat):
    """A 9-step heat rollout with a varying dt and a source per step: the gradient under ("revolve", s) equals
    autograd's through every step to 1e-12 relative, runs recomputed_steps(9, s) - (N - 1) steps again (the
    schedule's run of each step but the last before its reversal gives the state the previous reversal
    holds, so it is reused, not run), and holds the s snapshots and the working pair (N + 1 states when
    s >= N: every state)."""
    steps = 9
    g = torch.Generator().manual_seed(0)
    n = heat.problem.output_size
    u0 = 0.3 * torch.rand(2, n, dtype=torch.float64, generator=g)
    f = torch.rand(2, steps, heat.problem.control_size("f"), dtype=torch.float64, generator=g)
    weights = torch.rand(2, 2, n, dtype=torch.float64, generator=g)
    dts = np.linspace(0.005, 0.04, steps)

    def gradients(schedule):
        rollout = Rollout(heat, "u0", schedule=schedule)
        x, y = u0.clone().requires_grad_(), f.clone().requires_grad_()
        kappa = torch.ones(heat.problem.control_size("kappa"), dtype=torch.float64, requires_grad=True)
        u = rollout(x, steps, constants={"dt": dts}, per_step={"f": y}, kappa=kappa, outputs=[4, -1])
        (weights * u ** 2).sum().backward()
        return (x.grad, y.grad, kappa.grad), rollout.schedule_stats

    reference, _ = gradients("autograd")
    for s in (1, 2, 3, 5, 8, 9, 20):
        got, stats = gradients(("revolve", s))
        for a, b in zip(got, reference):
            scale = float(b.abs().max())
            assert scale > 0 and float((a - b).abs().max()) <= 1e-12 * scale, (s, float((a - b).abs().max()), scale)
        assert stats.steps == stats.adjoint_steps == steps, (s, stats)
        reused = steps - 1 if s < steps else 0
        assert stats.reused == reused and stats.recomputed == recomputed_steps(steps, s) - reused, (s, stats)
        assert stats.most_in_memory == (s + 2 if s < steps else steps + 1), (s, stats)
    assert recomputed_steps(steps, 1) == 36 and recomputed_steps(steps, 3) == 13      # the formula is not trivially 0
