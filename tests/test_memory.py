"""Memory stays flat: thousands of forward+backward calls, and hundreds of
layers created and closed, must not grow the process's resident memory.

Resident memory is read from /proc/self/status (VmRSS). Before each reading
the garbage collector runs and glibc's malloc_trim(0) hands free heap pages
back to the kernel; without that, a leak can hide in heap that earlier work
freed but glibc kept (measured: a deliberate 5 MiB leak moved VmRSS by 0.1 MiB).
``test_measurement_detects_a_leak`` checks that the measurement would see one.

Bounds: growth <= 5 % of the baseline and <= 4 MiB. A leak of one PETSc Vec
(81 doubles) or one small array per call would add 5-12 MiB over 5,000 calls.
"""
import gc
import subprocess
import sys
from pathlib import Path

from mpi4py import MPI
import dolfinx.mesh
import pytest
import torch
from petsc4py import PETSc

from fempdl import forms
from fempdl.bridge_torch import SolveLayer
from fempdl.ksp_adjoint import KSPOptions

from helpers import settled_rss

pytestmark = pytest.mark.skipif(
    not __import__("os").path.exists("/proc/self/status"), reason="needs /proc/self/status (Linux)")

F64 = torch.float64
MiB = 2**20
MAX_GROWTH_FRACTION = 0.05
MAX_GROWTH_BYTES = 4 * MiB
WARMUP_CALLS = 300
CALLS = 5000
BATCH = 4
K = 5


def live_petsc_objects() -> int:
    """petsc4py objects reachable by the garbage collector."""
    gc.collect()
    # type(o), not isinstance: isinstance reads __class__, which deprecated torch proxies warn about
    return sum(issubclass(type(o), PETSc.Object) for o in gc.get_objects())


def assert_flat(before: int, after: int, what: str) -> None:
    growth = after - before
    assert growth <= MAX_GROWTH_FRACTION * before, (
        f"{what}: VmRSS grew by {growth / MiB:.2f} MiB from {before / MiB:.1f} MiB (> 5 %)")
    assert growth <= MAX_GROWTH_BYTES, (
        f"{what}: VmRSS grew by {growth / MiB:.2f} MiB (> {MAX_GROWTH_BYTES / MiB:.0f} MiB)")


@pytest.fixture(scope="module")
def msh():
    return dolfinx.mesh.create_unit_square(MPI.COMM_WORLD, 8, 8)


@pytest.fixture(scope="module")
def prob_f(msh):
    """Poisson with f only: constant matrix, affine right-hand side."""
    return forms.poisson.problem(msh, controls=("f",))


@pytest.fixture(scope="module")
def prob_fk(msh):
    """Poisson with f and kappa (DG0): matrix and gradient form assembled per sample."""
    return forms.poisson.problem(msh, controls=("f", "kappa"), kappa_space="DG0")


def make_inputs(prob, gen):
    out = {"f": torch.rand(BATCH, prob.control_size("f"), dtype=F64, generator=gen).requires_grad_(True)}
    if "kappa" in prob.control_names:
        kappa = 1.0 + torch.rand(BATCH, prob.control_size("kappa"), dtype=F64, generator=gen)
        out["kappa"] = kappa.requires_grad_(True)
    return out


def run_calls(layer, prob, n, gen):
    for _ in range(n):
        inputs = make_inputs(prob, gen)
        u = layer(**inputs)
        (u * u).sum().backward()
        for t in inputs.values():
            assert t.grad is not None


@pytest.mark.parametrize("controls", ["f", "f+kappa"])
def test_forward_backward_calls_keep_memory_flat(prob_f, prob_fk, controls):
    prob = prob_f if controls == "f" else prob_fk
    layer = SolveLayer(prob, KSPOptions(ksp_type="richardson", pc_type="jacobi", max_it=K))
    gen = torch.Generator().manual_seed(1234)
    try:
        run_calls(layer, prob, WARMUP_CALLS, gen)
        petsc_before = live_petsc_objects()
        before = settled_rss()
        run_calls(layer, prob, CALLS, gen)
        after = settled_rss()
        assert_flat(before, after, f"{CALLS} forward+backward calls ({controls})")
        assert live_petsc_objects() == petsc_before
        # every sample was solved forward and backward with exactly K iterations
        n = (WARMUP_CALLS + CALLS) * BATCH
        stats = layer.stats
        assert stats.forward_solves == n and stats.backward_solves == n
        assert stats.forward_iterations == K * n and stats.backward_iterations == K * n
        assert stats.failures == 0
    finally:
        layer.close()


@pytest.mark.parametrize("how", ["close", "del"])
def test_creating_and_closing_layers_keeps_memory_flat(prob_fk, how):
    """200 layers, each used once (forward+backward, kappa a control), then closed or dropped."""
    gen = torch.Generator().manual_seed(5)

    def one_layer():
        layer = SolveLayer(prob_fk, KSPOptions(max_it=K))
        run_calls(layer, prob_fk, 1, gen)
        assert layer.stats.forward_solves == BATCH
        if how == "close":
            layer.close()
            layer.close()  # idempotent
        del layer

    for _ in range(20):
        one_layer()
    petsc_before = live_petsc_objects()
    before = settled_rss()
    for _ in range(200):
        one_layer()
    after = settled_rss()
    assert_flat(before, after, f"200 layers ({how})")
    assert live_petsc_objects() == petsc_before


def test_measurement_detects_a_leak():
    """The measurement above must see a leak of the size it is meant to catch:
    8 MiB kept in 8,192 small arrays (about 1 KiB each, like a per-call leak).
    Measured in a fresh process: here, the heap freed by earlier tests would
    serve the arrays from free chunks without moving VmRSS (2.4 MiB seen), and
    the self-test would measure the heap's history instead of the method."""
    code = (f"import sys; sys.path.insert(0, {str(Path(__file__).parent)!r})\n"
            "import numpy as np\n"
            "from helpers import settled_rss\n"
            "before = settled_rss()\n"
            "kept = [np.ones(128) for _ in range(8192)]\n"
            "print(settled_rss() - before, sum(a.size for a in kept))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    growth, size = map(int, done.stdout.split())
    assert size == 8192 * 128
    assert growth > MAX_GROWTH_BYTES, f"a deliberate 8 MiB leak moved VmRSS by {growth / MiB:.2f} MiB"
    # and PETSc objects kept alive are counted
    n0 = live_petsc_objects()
    vecs = [PETSc.Vec().createSeq(4, comm=PETSc.COMM_SELF) for _ in range(10)]
    assert live_petsc_objects() == n0 + 10
    for v in vecs:
        v.destroy()
