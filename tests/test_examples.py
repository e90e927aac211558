"""The scripts in examples/ run (on small meshes: FEMPDL_EXAMPLE_SMALL=1) and print what they claim."""
from __future__ import annotations

import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

EXAMPLES = Path(__file__).resolve().parent.parent / "examples"


def run_example(name: str, *args, cwd: Path) -> str:
    env = {**os.environ, "FEMPDL_EXAMPLE_SMALL": "1", "OMP_WAIT_POLICY": "PASSIVE", "OMP_NUM_THREADS": "1"}
    out = subprocess.run([sys.executable, str(EXAMPLES / name), *map(str, args)], cwd=cwd, env=env,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.py")))
def test_examples_are_short(name):
    assert len((EXAMPLES / name).read_text().splitlines()) <= 60


def test_custom_problem_in_a_module_trained_with_adam(tmp_path):
    stdout = run_example("custom_problem.py", cwd=tmp_path)
    m = re.fullmatch(r"loss (\S+) -> (\S+); kappa error (\S+); solves (\d+)\n", stdout)
    assert m, stdout
    first, last, kappa_error, solves = float(m[1]), float(m[2]), float(m[3]), int(m[4])
    assert last < first / 50 and kappa_error < 0.1
    assert solves == 8 + 40 * 8          # the observations, then 40 steps of a batch of 8


def test_prdp_loop_raises_k_up_to_k_eps(tmp_path):
    stdout = run_example("prdp_loop.py", cwd=tmp_path)
    m = re.fullmatch(r"K_eps (\d+); K per epoch \[([\d, ]+)\]; capped validations at K \[([\d, ]*)\]; finished at "
                     r"K (\d+) from (\d+) \(gap (\S+), probes \[([\d, ]*)\]\)\n"
                     r"validation nMSE (\S+); solver iterations (\d+); converged validations (\d+)\n", stdout)
    assert m, stdout
    keps, schedule, iterations = int(m[1]), [int(k) for k in m[2].split(",")], int(m[9])
    capped = [int(k) for k in m[3].split(",") if k.strip()]
    probes = [int(k) for k in m[7].split(",") if k.strip()]
    assert len(schedule) == 30 and schedule[0] == 1 and schedule[-1] > 1
    assert all(a <= b for a, b in zip(schedule, schedule[1:])) and max(schedule) <= keps
    assert float(m[6]) <= 0.05 and int(m[5]) <= int(m[4]) <= keps          # finished with the gap closed
    # per epoch: 32 training samples forward and backward at K; the validation's 8 samples at converged
    # physics (counted apart), and at the caps: at K every step, and at each probe of a search; finish once more
    assert iterations == (32 + 32) * sum(schedule) + 8 * (sum(capped) + int(m[5]) + sum(probes))
    assert int(m[10]) == 8 * 31


def test_write_fields_writes_prediction_reference_and_flow(tmp_path):
    stdout = run_example("write_fields.py", tmp_path / "out", cwd=tmp_path)
    m = re.search(r"relative error at K = 1 \.\.\. 32: (\S+) \.\.\. (\S+)\n", stdout)
    assert m and float(m[2]) < float(m[1]) < 1.0, stdout
    for name, fields, times in (("poisson", {"prediction", "reference", "error", "f"}, [1, 2, 4, 8, 16, 32]),
                                ("stokes", {"flow_u", "flow_p"}, [0])):
        xdmf = tmp_path / "out" / f"{name}.xdmf"
        assert (tmp_path / "out" / f"{name}.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
        root = ET.parse(xdmf).getroot()
        written = {(a.get("Name"), float(g.find("Time").get("Value")))
                   for g in root.iter("Grid") if g.find("Time") is not None for a in g.findall("Attribute")}
        assert written == {(field, float(t)) for field in fields for t in times}
    assert float(re.search(r"\|u\|_max (\S+)", stdout)[1]) > 1e-3


def test_learn_material_through_newton_solves(tmp_path):
    stdout = run_example("learn_material.py", cwd=tmp_path)
    m = re.fullmatch(r"loss (\S+) -> (\S+); kappa error (\S+); newton steps (\d+) in (\d+) solves\n", stdout)
    assert m, stdout
    first, last, kappa_error, steps, solves = float(m[1]), float(m[2]), float(m[3]), int(m[4]), int(m[5])
    assert last < first / 4 and kappa_error < 0.25
    assert solves == 8 + 80 * 8            # the observations, then 80 steps of a batch of 8
    assert 2 * solves <= steps <= 8 * solves   # converged Newton: a few quadratic steps per solve


def test_learn_conductivity_fits_the_law_through_the_network_in_the_form(tmp_path):
    stdout = run_example("learn_conductivity.py", cwd=tmp_path)
    m = re.fullmatch(r"loss (\S+); kappa error (\S+) over u in \[0, (\S+)\]; network time (\d+)% of the layer's\n",
                     stdout)
    assert m, stdout
    assert float(m[1]) < 0.02 and float(m[2]) < 0.5 and float(m[3]) > 0.3      # 40 epochs on the coarse plate
    assert 0 < int(m[4]) < 100


def test_learn_energy_fits_a_neo_hookean_beam(tmp_path):
    stdout = run_example("learn_energy.py", cwd=tmp_path)
    m = re.fullmatch(r"loss (\S+); energy error (\S+) near F = I; newton steps (\d+) in (\d+) solves\n", stdout)
    assert m, stdout
    assert float(m[1]) < 0.05 and float(m[2]) < 0.3
    assert int(m[4]) == 30 * 3 and int(m[3]) >= int(m[4])        # 30 epochs of 3 loads (the reference apart)
