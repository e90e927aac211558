"""The committed benchmark records keep the harness's keys, and every benchmark script goes through the harness.

Plain file checks (no FE import): every ``bench-results/*.json`` is valid JSON whose top-level keys
begin with ``bench_common.REPORT_KEYS``; its ``"load"`` has ``"start"`` and ``"end"`` lists of three
load averages; its ``"statistic"`` is null or one of ``bench_common.STATISTICS``. Every
``benchmarks/bench_*.py`` and ``demo_*.py`` builds its options with ``bench_common.parser(...)`` and
writes inside ``bench_common.report(...)``; no file of ``benchmarks/`` is over 400 lines.
``bench_common`` is loaded by path: it imports DOLFINx, PETSc, MPI and torch only inside its functions.

A few records were measured before the harness and migrated to its keys (39cdf74): they are exempt
from exactly the rule they break, named in :data:`KEY_ORDER_EXEMPT` and :data:`NO_END_LOAD`. Once such
a record is measured again it fits, and the test asks for its exemption to go.
"""
from __future__ import annotations

import ast
import datetime
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BENCHMARKS = ROOT / "benchmarks"
RESULTS = ROOT / "bench-results"
MAX_LINES = 400
FE_MODULES = ("dolfinx", "petsc4py", "mpi4py", "torch", "ufl", "fempdl")

#: Records whose top-level keys hold every report key but not in the report's order.
KEY_ORDER_EXEMPT: dict[str, str] = {}
#: Records whose ``load["end"]`` is null: measured before the harness recorded the load at the end.
NO_END_LOAD = {
    "bench_pc_transpose_current.json": "measured 2026-11-23, before the harness",
    "bench_sip.json": "measured 2026-11-23, before the harness",
    "bench_stacks.json": "measured 2026-11-23, before the harness",
}


def load_bench_common():
    """``benchmarks/bench_common.py`` as a module, loaded by path; the OpenMP default it sets is undone."""
    policy = os.environ.get("OMP_WAIT_POLICY")
    spec = importlib.util.spec_from_file_location("_bench_common_of_the_records_test", BENCHMARKS / "bench_common.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module              # its dataclasses look their module up there
    try:
        spec.loader.exec_module(module)
    finally:
        del sys.modules[spec.name]
        if policy is None:
            os.environ.pop("OMP_WAIT_POLICY", None)
        else:
            os.environ["OMP_WAIT_POLICY"] = policy
    return module


bench_common = load_bench_common()
REPORT_KEYS = tuple(bench_common.REPORT_KEYS)
STATISTICS = tuple(bench_common.STATISTICS)


# ------------------------------------------------------------------ the checkers
def _is_load(value) -> bool:
    """Three load averages (1, 5 and 15 minutes)."""
    return (isinstance(value, list) and len(value) == 3
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and x >= 0 for x in value))


def record_problems(record, *, key_order_exempt: bool = False, no_end_load: bool = False) -> list[str]:
    """What is wrong with one parsed record (empty if nothing); the flags allow the two exemptions."""
    if not isinstance(record, dict):
        return [f"the top level is a {type(record).__name__}, not an object"]
    problems = []
    keys = list(record)
    if key_order_exempt:
        missing = [k for k in REPORT_KEYS if k not in record]
        if missing:
            problems.append(f"report keys missing: {missing}")
    elif tuple(keys[:len(REPORT_KEYS)]) != REPORT_KEYS:
        problems.append(f"top-level keys begin {keys[:len(REPORT_KEYS)]}, not {list(REPORT_KEYS)}")
    if "benchmark" in record and not (isinstance(record["benchmark"], str) and record["benchmark"]):
        problems.append(f'"benchmark" is {record["benchmark"]!r}, not a script name')
    if "date" in record:
        try:
            datetime.datetime.fromisoformat(record["date"])
        except (TypeError, ValueError):
            problems.append(f'"date" is {record["date"]!r}, not an ISO date')
    if "machine" in record and not isinstance(record["machine"], dict):
        problems.append(f'"machine" is {record["machine"]!r}, not an object')
    if "load" in record:
        load = record["load"]
        if not isinstance(load, dict):
            problems.append(f'"load" is {load!r}, not an object')
        else:
            if not _is_load(load.get("start")):
                problems.append(f'load["start"] is {load.get("start")!r}, not a list of 3 load averages')
            end = load.get("end", "missing")
            if not (_is_load(end) or (no_end_load and end is None)):
                problems.append(f'load["end"] is {end!r}, not a list of 3 load averages')
    if "statistic" in record and record["statistic"] is not None and record["statistic"] not in STATISTICS:
        problems.append(f'"statistic" is {record["statistic"]!r}, not null or one of {list(STATISTICS)}')
    if "repeats" in record:
        repeats = record["repeats"]
        if repeats is not None and not (isinstance(repeats, int) and not isinstance(repeats, bool) and repeats >= 1):
            problems.append(f'"repeats" is {repeats!r}, not null or an integer >= 1')
    return problems


def file_problems(path: Path, *, strict: bool = False) -> list[str]:
    """What is wrong with the record in ``path``; ``strict``: without its exemptions."""
    try:
        record = json.loads(path.read_text(encoding="utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        return [f"not valid JSON: {err}"]
    return record_problems(record, key_order_exempt=not strict and path.name in KEY_ORDER_EXEMPT,
                           no_end_load=not strict and path.name in NO_END_LOAD)


def _calls_to(tree: ast.AST, name: str) -> list[ast.Call]:
    """Calls of ``bench_common.<name>(...)``, or of ``<name>(...)`` where ``from bench_common import <name>``."""
    imported = any(isinstance(node, ast.ImportFrom) and node.module == "bench_common"
                   and any(alias.name == name and alias.asname is None for alias in node.names)
                   for node in ast.walk(tree))
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            f = node.func
            if (isinstance(f, ast.Attribute) and f.attr == name and isinstance(f.value, ast.Name)
                    and f.value.id == "bench_common") or (imported and isinstance(f, ast.Name) and f.id == name):
                found.append(node)
    return found


def script_problems(path: Path) -> list[str]:
    """What a benchmark script lacks of the harness: its parser, its report."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    problems = []
    if not _calls_to(tree, "parser"):
        problems.append(f"{path.name} does not build its options with bench_common.parser(...)")
    if not _calls_to(tree, "report"):
        problems.append(f"{path.name} does not write its JSON through bench_common.report(...)")
    return problems


RECORDS = sorted(RESULTS.glob("*.json"))
SCRIPTS = sorted(p for pattern in ("bench_*.py", "demo_*.py") for p in BENCHMARKS.glob(pattern)
                 if p.name != "bench_common.py")


# ------------------------------------------------------------------ the records and the scripts
def test_there_are_records_and_scripts():
    assert RECORDS, f"no benchmark records in {RESULTS}"
    assert SCRIPTS, f"no benchmark scripts in {BENCHMARKS}"


@pytest.mark.parametrize("path", RECORDS, ids=[p.name for p in RECORDS])
def test_record_has_the_report_keys(path):
    problems = file_problems(path)
    assert not problems, f"bench-results/{path.name}: " + "; ".join(problems)


@pytest.mark.parametrize("name", sorted({*KEY_ORDER_EXEMPT, *NO_END_LOAD}))
def test_every_exemption_is_still_needed(name):
    path = RESULTS / name
    assert path.exists(), f"bench-results/{name} is gone: drop it from the exemptions in {Path(__file__).name}"
    strict = file_problems(path, strict=True)
    if name in KEY_ORDER_EXEMPT:
        assert any("top-level keys" in p for p in strict), \
            f"bench-results/{name} now has the report's key order: drop it from KEY_ORDER_EXEMPT"
    if name in NO_END_LOAD:
        assert any('load["end"]' in p for p in strict), \
            f"bench-results/{name} now records the end load: drop it from NO_END_LOAD"


@pytest.mark.parametrize("path", SCRIPTS, ids=[p.name for p in SCRIPTS])
def test_script_uses_the_harness(path):
    problems = script_problems(path)
    assert not problems, "; ".join(problems)


def test_no_benchmark_module_is_over_400_lines():
    long = {p.name: n for p in sorted(BENCHMARKS.glob("*.py")) if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"benchmarks/ modules over {MAX_LINES} lines (split them by idea): {long}"


def test_bench_common_loads_no_fe_stack():
    """Loading bench_common (as this test and the benchmarks' workers do) imports none of the FE stack."""
    code = ("import importlib.util, sys\n"
            f"spec = importlib.util.spec_from_file_location('bc', {str(BENCHMARKS / 'bench_common.py')!r})\n"
            "sys.modules['bc'] = module = importlib.util.module_from_spec(spec)\n"
            "spec.loader.exec_module(module)\n"
            f"print(sorted(m for m in {FE_MODULES!r} if m in sys.modules))\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


# ------------------------------------------------------------------ the checkers catch what they should
def good_record() -> dict:
    return {"benchmark": "bench_x", "date": "2026-11-29T01:50:05+00:00", "machine": {"cpu_count": 2},
            "load": {"start": [0.5, 0.4, 0.3], "end": [1, 1.0, 0.9], "during": []},
            "statistic": "min", "repeats": 3, "results": []}


def test_the_record_checker_catches_bad_records(tmp_path):
    assert record_problems(good_record()) == []
    assert record_problems({**good_record(), "statistic": None, "repeats": None}) == []
    assert "not an object" in record_problems([1, 2])[0]

    reordered = {k: v for k, v in good_record().items() if k != "date"} | {"date": "2026-11-29"}
    assert any("top-level keys begin" in p for p in record_problems(reordered))
    assert record_problems(reordered, key_order_exempt=True) == []
    missing = {k: v for k, v in good_record().items() if k != "machine"}
    assert any("top-level keys begin" in p for p in record_problems(missing))
    assert any("report keys missing: ['machine']" in p for p in record_problems(missing, key_order_exempt=True))

    def with_load(**load):
        return {**good_record(), "load": load}

    assert any('load["end"] is None' in p for p in record_problems(with_load(start=[1, 1, 1], end=None)))
    assert record_problems(with_load(start=[1, 1, 1], end=None), no_end_load=True) == []
    assert any('load["end"] is \'missing\'' in p for p in record_problems(with_load(start=[1, 1, 1])))
    assert any('load["start"]' in p for p in record_problems(with_load(start=[1, 1], end=[1, 1, 1])))
    assert any('load["start"]' in p for p in record_problems(with_load(start=[1, "x", 1], end=[1, 1, 1])))
    assert any('load["start"]' in p for p in record_problems(with_load(start=[True, 1, 1], end=[1, 1, 1])))
    assert any('"load" is' in p for p in record_problems({**good_record(), "load": [1, 1, 1]}))
    assert any('"statistic"' in p for p in record_problems({**good_record(), "statistic": "fastest"}))
    assert any('"repeats"' in p for p in record_problems({**good_record(), "repeats": 0}))
    assert any('"date"' in p for p in record_problems({**good_record(), "date": "yesterday"}))

    bad = tmp_path / "bench_broken.json"
    bad.write_text('{"benchmark": "bench_broken",')
    assert "not valid JSON" in file_problems(bad)[0]
    bad.write_text(json.dumps({**good_record(), "statistic": "p90"}))
    assert any('"statistic"' in p for p in file_problems(bad))


def test_the_script_checker_catches_a_script_without_the_harness(tmp_path):
    source = (BENCHMARKS / "bench_layer.py").read_text()
    assert "bench_common.parser(" in source and "bench_common.report(" in source
    assert script_problems(BENCHMARKS / "bench_layer.py") == []

    no_report = tmp_path / "bench_no_report.py"
    no_report.write_text(source.replace("bench_common.report(", "write_my_own_json("))
    assert script_problems(no_report) == ["bench_no_report.py does not write its JSON through bench_common.report(...)"]
    with pytest.raises(AssertionError, match="bench_no_report.py does not write its JSON"):
        test_script_uses_the_harness(no_report)

    no_parser = tmp_path / "bench_no_parser.py"
    no_parser.write_text(source.replace("bench_common.parser(", "argparse.ArgumentParser("))
    assert script_problems(no_parser) == ["bench_no_parser.py does not build its options with bench_common.parser(...)"]

    imported = tmp_path / "bench_imported.py"
    imported.write_text("from bench_common import parser, report\n\n"
                        "def main():\n    args = parser(__file__, None, repeats=1, quick='').parse_args()\n"
                        "    with report(__file__, args.out, repeats=1):\n        pass\n")
    assert script_problems(imported) == []
    local = tmp_path / "bench_local.py"
    local.write_text("import bench_common\n\ndef report(row):\n    print(row)\n\n"
                     "def main():\n    bench_common.parser(__file__, None, repeats=1, quick='')\n    report({})\n")
    assert script_problems(local) == ["bench_local.py does not write its JSON through bench_common.report(...)"]
