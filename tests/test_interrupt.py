"""Ctrl-C stops what fempdl runs with a KeyboardInterrupt, as it stops any Python loop.

gmsh's Python module sets SIGINT to the OS default when imported, which made Ctrl-C kill a process
whose first fempdl import was ``mesh`` (no ``finally``, no checkpoint); and a Newton layer's long
inner solve never came back to Python, so Ctrl-C went unanswered until it ended. Each test runs a
child process, interrupts it, and checks that it unwound through KeyboardInterrupt.
"""
from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

MARKER = "finally ran"


def _interruptible_child() -> None:
    """A child's SIGINT as a terminal gives it: unblocked, default disposition (Python then installs
    KeyboardInterrupt), whatever this test process inherited."""
    signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def interrupt(code: str, *, wait: float = 20.0) -> tuple[int, str, str]:
    """Run ``code`` in a child, send SIGINT 0.5 s after it prints "ready", and give it ``wait``
    seconds to end; (returncode, stdout, stderr). A child still running then is killed and fails."""
    child = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True, env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"},
                             preexec_fn=_interruptible_child)
    try:
        first = child.stdout.readline()
        assert first.strip() == "ready", first + child.stderr.read()[-3000:]
        time.sleep(0.5)
        child.send_signal(signal.SIGINT)
        try:
            out, err = child.communicate(timeout=wait)
        except subprocess.TimeoutExpired:
            child.kill()
            out, err = child.communicate()
            pytest.fail(f"still running {wait} s after SIGINT: Ctrl-C was not answered\n{out}\n{err[-3000:]}")
    finally:
        if child.poll() is None:
            child.kill()
            child.communicate()
    return child.returncode, out, err


LOOP = f"""
print("ready", flush=True)
try:
    while True:
        sum(range(1000))
finally:
    print({MARKER!r}, flush=True)
"""


@pytest.mark.parametrize("first_import", [
    "from fempdl import mesh",
    "import fempdl.mesh as mesh",
    "from fempdl.core import meshgen, mesh",
])
def test_ctrl_c_in_a_loop_after_loading_a_mesh_raises_keyboard_interrupt(first_import):
    """The mesh module imported first, a bundled mesh loaded (and one meshed by gmsh): the loop's
    ``finally`` runs and the process ends with a KeyboardInterrupt traceback, not killed by SIGINT."""
    code = (f"{first_import}\n"
            "mesh.load('lshape')\n"
            "mesh.load('lshape', h=0.5)\n" + LOOP)
    returncode, out, err = interrupt(code)
    assert MARKER in out, (returncode, out, err[-3000:])
    assert err.rstrip().endswith("KeyboardInterrupt"), err[-3000:]


def test_ctrl_c_after_importing_gmsh_before_fempdl_raises_keyboard_interrupt():
    """gmsh used first, as a user meshing their own geometry does (``import gmsh`` sets the OS default in
    Debian's gmsh, ``gmsh.initialize()`` in later releases): ``import fempdl`` puts Python's handler back,
    and loading a mesh through fempdl keeps it."""
    code = ("import gmsh, signal\n"
            "signal.signal(signal.SIGINT, signal.SIG_DFL)   # what gmsh left, whichever release\n"
            "import fempdl\n"
            "from fempdl import mesh\n"
            "mesh.load('lshape', h=0.5)\n" + LOOP)
    returncode, out, err = interrupt(code)
    assert MARKER in out, (returncode, out, err[-3000:])
    assert err.rstrip().endswith("KeyboardInterrupt"), err[-3000:]


def test_a_handler_the_user_installed_survives_importing_and_meshing():
    """Whatever SIGINT handler was in place before fempdl imported gmsh stays in place, through
    imports, a bundled load and a gmsh meshing session."""
    code = ("import signal\n"
            "def mine(signum, frame):\n"
            "    raise SystemExit('mine')\n"
            "signal.signal(signal.SIGINT, mine)\n"
            "from fempdl import mesh, io\n"
            "import fempdl.core.meshgen, fempdl.core._dolfinx\n"
            "assert signal.getsignal(signal.SIGINT) is mine, signal.getsignal(signal.SIGINT)\n"
            "mesh.load('lshape'); mesh.load('lshape', h=0.5)\n"
            "assert signal.getsignal(signal.SIGINT) is mine, signal.getsignal(signal.SIGINT)\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "OMP_WAIT_POLICY": "PASSIVE"}, preexec_fn=_interruptible_child)
    assert done.returncode == 0, done.stderr[-3000:]


NEWTON = """
import torch
from mpi4py import MPI
from fempdl import KSPOptions, NewtonOptions, NonlinearSolveLayer, forms, mesh
# h = 0.03 (4k DOFs): a budget Newton solve stops at its tolerance, and with one Jacobi sweep per step it
# converges in about 0.4 s at h = 0.1, often before the SIGINT (sent 0.5 s after "ready") arrives; here it
# runs for minutes.
prob = forms.nonlinear_diffusion.problem(mesh.load("lshape", MPI.COMM_SELF, h=0.03), controls=("f",))
layer = NonlinearSolveLayer(prob, NewtonOptions(max_it={max_it}, ksp=KSPOptions.preset("jacobi", max_it={inner})))
f = torch.ones(prob.control_size("f"), dtype=torch.float64)
print("ready", flush=True)
try:
    layer(f=f)
except KeyboardInterrupt:
    print("KeyboardInterrupt", flush=True)
# The same layer solves again once its caps are small (moving the Newton cap keeps the SNES and its KSP).
layer.max_it = 3
if layer.inner_max_it > 50:
    layer.inner_max_it = 50
u = layer(f=f)
print("next solve", layer.stats.last_newton.steps, bool(torch.isfinite(u).all()), flush=True)
"""


@pytest.mark.parametrize("max_it, inner", [
    (None, 10 ** 9),        # hours of Jacobi iterations in the first Newton step's inner solve
    (5, 10 ** 9),
    (10 ** 8, 1),           # 10^8 short Newton steps: the residual and Jacobian callbacks are Python
])
def test_ctrl_c_stops_a_newton_layer(max_it, inner):
    """A Newton layer stops on SIGINT with KeyboardInterrupt, within a long inner solve (a monitor on
    long solves, the linear layer's rule) or between its steps, and its next solve works (the
    interrupted SNES is renewed)."""
    returncode, out, err = interrupt(NEWTON.format(max_it=max_it, inner=inner))
    assert returncode == 0, err[-3000:]
    assert out.splitlines() == ["KeyboardInterrupt", "next solve 3 True"], (out, err[-3000:])


def test_a_matrix_interrupted_while_assembled_takes_the_next_assembly(coarse_lshape, monkeypatch):
    """Ctrl-C between setting a matrix's values and assembling them left it unassembled, and PETSc refuses
    to zero such a matrix: every later solve of the layer failed with PETSc error 73. The interrupt now
    finishes the assembly on its way out, and the next solve is the one a fresh layer gives."""
    import torch
    from petsc4py import PETSc

    from fempdl import SolveLayer, forms
    from fempdl.core import _dolfinx

    prob = forms.poisson.problem(coarse_lshape, controls=("f", "kappa"))
    layer = SolveLayer(prob, "lu")
    f = torch.ones(prob.control_size("f"), dtype=torch.float64)
    kappa = torch.ones(prob.control_size("kappa"), dtype=torch.float64)
    layer(f=f, kappa=kappa)

    def interrupted(*args):
        # Half-way: the entries summed so far, a value set through PETSc and not yet assembled.
        layer.system._A.setValue(0, 0, 1.0, addv=PETSc.InsertMode.ADD_VALUES)
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        # Both assembly paths: through PETSc, and DOLFINx's CSR assembly into the arrays PETSc shares.
        patch.setattr(_dolfinx, "assemble_petsc_matrix", interrupted)
        patch.setattr(_dolfinx, "assemble_csr_matrix", interrupted)
        with pytest.raises(KeyboardInterrupt):
            layer(f=f, kappa=2 * kappa)
    u = layer(f=f, kappa=2 * kappa)
    fresh = SolveLayer(prob, "lu")
    torch.testing.assert_close(u, fresh(f=f, kappa=2 * kappa), rtol=0, atol=1e-12)
    fresh.close()
    layer.close()
