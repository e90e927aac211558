"""The `fempdl` command: scenes, run (PRDP / fixed K / converged / resume), tradeoff, and its errors.

All runs use a tiny emulator scene (coarse L-shape, 16 training samples) and
are shared between tests through module-scoped fixtures.
"""
from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import json
import math
import re
import sys
from pathlib import Path

import pytest

from fempdl.app import cli, scene, schema
from fempdl.app.runs import runner

from helpers import CLI_TINY, tiny_scene

TRAIN, BATCH, EPOCHS = 16, 8, 6
TINY = tiny_scene("emulator", CLI_TINY, data={"train": TRAIN}, optimizer={"epochs": EPOCHS, "batch": BATCH})
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def call(argv) -> tuple[int, str, str]:
    """cli.main(argv) with stdout and stderr captured (usable from module-scoped fixtures)."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = cli.main([str(a) for a in argv])
    return code, out.getvalue(), err.getvalue()


ROW = re.compile(r"^(?P<label>\S+) +(?P<schedule>.*?) +(?P<metric>\S+e[+-]\d+) +(?P<its>[\d,]+) +(?P<wall>[\d.]+)"
                 r"(?: +(?P<rel_its>[\d.]+x) +(?P<rel_time>[\d.]+x))? *$")


def table_rows(text: str) -> dict[str, dict]:
    """The comparison table's rows by label: K schedule, metric, iterations, time, ratios to the baseline."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("run ") and "K schedule" in line)
    assert set(lines[start + 1]) == {"-"}
    rows = {}
    for line in lines[start + 2:]:
        match = ROW.match(line)
        if match is None:
            break
        rows[match["label"]] = {"schedule": match["schedule"].split(), "metric": float(match["metric"]),
                                "its": int(match["its"].replace(",", "")), "wall": float(match["wall"]),
                                "rel_its": match["rel_its"], "rel_time": match["rel_time"]}
    return rows


def metrics(run_dir: Path) -> list[dict]:
    return json.loads((run_dir / "metrics.json").read_text())


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("scene") / "tiny.toml"
    path.write_text(TINY)
    assert scene.load(path).optimizer.epochs == EPOCHS
    return path


@pytest.fixture(scope="module")
def default_run(tiny, tmp_path_factory):
    """`fempdl run tiny.toml`: PRDP plus the converged baseline."""
    out = tmp_path_factory.mktemp("run") / "out"
    code, stdout, stderr = call(["run", tiny, "--out", out, "--no-progress"])
    return {"code": code, "stdout": stdout, "stderr": stderr, "out": out}


@pytest.fixture(scope="module")
def tradeoff_run(tiny, tmp_path_factory):
    out = tmp_path_factory.mktemp("tmp") / "tr"
    code, stdout, stderr = call(["tradeoff", tiny, "--ks", "1,2", "--epochs", "4", "--out", out, "--no-progress"])
    return {"code": code, "stdout": stdout, "stderr": stderr, "out": out}


# ------------------------------------------------------------------ scenes
def test_scenes_lists_every_bundled_scene(capsys):
    assert cli.main(["scenes"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = scene.available()
    assert len(names) >= 4
    assert [line.split()[0] for line in lines] == names
    for line, name in zip(lines, names):
        assert line.endswith(scene.load(name).description)


# ------------------------------------------------------------------ run (PRDP + baseline)
def test_run_prints_prdp_and_baseline_rows(default_run):
    assert default_run["code"] == 0, default_run["stderr"]
    stdout = default_run["stdout"]
    assert stdout.startswith("scene tiny-emulator: tiny heat emulator for the CLI tests\n")
    rows = table_rows(stdout)
    keps = metrics(default_run["out"] / "converged")[-1]["k"]
    assert list(rows) == ["PRDP", f"K_eps={keps}"]
    prdp, base = rows["PRDP"], rows[f"K_eps={keps}"]
    assert base["schedule"] == [str(keps)] and base["rel_its"] == "1.00x" and base["rel_time"] == "1.00x"
    last_prdp = metrics(default_run["out"] / "prdp")[-1]
    last_base = metrics(default_run["out"] / "converged")[-1]
    assert prdp["its"] == last_prdp["total_iterations"]
    assert base["its"] == last_base["total_iterations"]
    assert prdp["metric"] == pytest.approx(last_prdp["val_metric"], rel=1e-3)
    assert base["metric"] == pytest.approx(last_base["val_metric"], rel=1e-3)
    assert prdp["rel_its"] == f"{last_prdp['total_iterations'] / last_base['total_iterations']:.2f}x"
    assert f"metrics, checkpoints and time_split.png in {default_run['out']}" in stdout


def test_run_writes_metrics_and_checkpoints(default_run):
    out = default_run["out"]
    assert sorted(p.name for p in out.iterdir()) == [".fempdl-record.json", "converged", "prdp", "time_split.png"]
    for sub in ("prdp", "converged"):
        names = {p.name for p in (out / sub).iterdir()}
        assert {"metrics.csv", "metrics.json", "checkpoint.pt"} <= names
        assert not [n for n in names if n.startswith(".") and n != ".fempdl-record.json"], names  # no temporary files
        with (out / sub / "metrics.csv").open() as fh:
            from_csv = list(csv.DictReader(fh))
        from_json = metrics(out / sub)
        assert [int(r["epoch"]) for r in from_csv] == [r["epoch"] for r in from_json] == list(range(EPOCHS))
        assert [int(r["total_iterations"]) for r in from_csv] == [r["total_iterations"] for r in from_json]
        assert [int(r["k"]) for r in from_csv] == [r["k"] for r in from_json]


def test_prdp_iteration_accounting(default_run):
    rows = metrics(default_run["out"] / "prdp")
    keps = metrics(default_run["out"] / "converged")[-1]["k"]
    assert [r["epoch"] for r in rows] == list(range(EPOCHS))
    ks = [r["k"] for r in rows]
    assert ks[0] == 1  # k0
    assert ks == sorted(ks) and ks[-1] <= keps
    assert all((b - a) in (0, 2) or b == keps for a, b in zip(ks, ks[1:]))  # dk = 2, capped at K_eps
    for epoch, row in enumerate(rows):
        # Every training sample passes the layer once per epoch, forward and backward.
        expected = TRAIN * sum(ks[:epoch + 1])
        assert row["forward_iterations"] == row["backward_iterations"] == expected
        assert row["total_iterations"] == row["forward_iterations"] + row["backward_iterations"]
        assert math.isfinite(row["train_loss"]) and row["train_loss"] > 0
        assert math.isfinite(row["val_metric"]) and row["val_metric"] > 0
    assert [r["wall_time"] for r in rows] == sorted(r["wall_time"] for r in rows)


def test_converged_baseline_iteration_accounting(default_run):
    rows = metrics(default_run["out"] / "converged")
    keps = rows[0]["k"]
    assert keps > 1
    for epoch, row in enumerate(rows):
        assert row["k"] == keps
        assert row["forward_iterations"] == row["backward_iterations"] == TRAIN * keps * (epoch + 1)
        assert row["total_iterations"] == 2 * TRAIN * keps * (epoch + 1)


def test_resume_of_a_finished_run_does_not_train_again(default_run, tiny):
    out = default_run["out"]
    files = [out / sub / name for sub in ("prdp", "converged") for name in ("metrics.json", "metrics.csv",
                                                                            "checkpoint.pt")]
    before = {f: (f.read_bytes(), f.stat().st_mtime_ns) for f in files}
    code, stdout, stderr = call(["run", tiny, "--out", out, "--resume", "--no-progress"])
    assert code == 0, stderr
    assert table_rows(stdout) == table_rows(default_run["stdout"])
    for f in files:
        assert (f.read_bytes(), f.stat().st_mtime_ns) == before[f], f


# ------------------------------------------------------------------ other modes
def test_fixed_k_run(tiny, tmp_path):
    out = tmp_path / "out"
    code, stdout, stderr = call(["run", tiny, "--k", "3", "--epochs", "3", "--no-baseline", "--out", out,
                                 "--no-progress"])
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == [".fempdl-record.json", "k3", "time_split.png"]
    rows = metrics(out / "k3")
    assert [r["epoch"] for r in rows] == [0, 1, 2]  # --epochs overrides the scene's 6
    for epoch, row in enumerate(rows):
        assert row["k"] == 3
        assert row["forward_iterations"] == row["backward_iterations"] == TRAIN * 3 * (epoch + 1)
    table = table_rows(stdout)
    assert list(table) == ["K=3"]
    assert table["K=3"]["schedule"] == ["3"] and table["K=3"]["its"] == 2 * TRAIN * 3 * 3
    assert table["K=3"]["rel_its"] is None and table["K=3"]["rel_time"] is None  # no baseline, no ratios


def test_converged_only(tiny, tmp_path):
    out = tmp_path / "out"
    code, stdout, stderr = call(["run", tiny, "--converged", "--epochs", "2", "--out", out, "--no-progress"])
    assert code == 0, stderr
    assert sorted(p.name for p in out.iterdir()) == [".fempdl-record.json", "converged", "time_split.png"]
    rows = metrics(out / "converged")
    keps = rows[0]["k"]
    assert [r["k"] for r in rows] == [keps, keps]
    assert list(table_rows(stdout)) == [f"K_eps={keps}"]
    assert "PRDP" not in stdout


# ------------------------------------------------------------------ errors
def test_unknown_scene_returns_2_and_names_the_bundled_scenes(capsys):
    assert cli.main(["run", "no-such-scene"]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("fempdl: unknown scene 'no-such-scene'; bundled scenes are")
    for name in scene.available():
        assert repr(name) in captured.err


def test_missing_scene_file_returns_2(tmp_path, capsys):
    missing = tmp_path / "nope.toml"
    assert cli.main(["tradeoff", str(missing)]) == 2
    assert f"scene file {str(missing)!r} does not exist" in capsys.readouterr().err


def test_bad_scene_file_returns_2_with_the_scene_error(tmp_path, capsys):
    path = tmp_path / "bad.toml"
    path.write_text(tiny_scene("emulator", CLI_TINY, optimizer={"lr": -1e-3}))
    assert cli.main(["run", str(path), "--out", str(tmp_path / "out")]) == 2
    assert f"fempdl: {path}: [optimizer] lr must be > 0, got -0.001" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("argv, fragment", [
    (["run", "--k", "0"], "argument --k: must be >= 1, got 0"),
    (["run", "--k", "x"], "argument --k: expected an integer, got 'x'"),
    (["run", "--k", "3", "--prdp"], "argument --prdp: not allowed with argument --k"),
    (["run", "--k", "3", "--converged"], "argument --converged: not allowed with argument --k"),
    (["run", "--epochs", "0"], "argument --epochs: must be >= 1, got 0"),
    (["tradeoff", "x", "--ks", "1,0"], "argument --ks: must be >= 1, got 0"),
    (["tradeoff", "x", "--ks", ","], "argument --ks: expected comma-separated ints >= 1, got ','"),
    (["tradeoff"], "the following arguments are required: scene"),
    ([], "the following arguments are required: command"),
])
def test_argument_errors_exit_2(argv, fragment, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main(argv)
    assert info.value.code == 2
    assert fragment in capsys.readouterr().err


# ------------------------------------------------------------------ tradeoff
def test_tradeoff_writes_its_report(tradeoff_run):
    assert tradeoff_run["code"] == 0, tradeoff_run["stderr"]
    out = tradeoff_run["out"]
    for name in ("tradeoff.json", "tradeoff.csv"):
        assert (out / name).is_file()
    for name in ("metric_per_epoch.png", "metric_vs_cost.png", "time_split.png"):
        data = (out / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE), name
        assert len(data) > 5_000, (name, len(data))
    stdout = tradeoff_run["stdout"]
    assert "wrote " in stdout and str(out / "tradeoff.json") in stdout
    report = json.loads((out / "tradeoff.json").read_text())
    table = table_rows(stdout)
    assert list(table) == list(report["runs"])
    for label, row in table.items():
        assert row["its"] == report["runs"][label]["total_iterations"]
    split = report["savings"]
    assert (f"K_eps = {split['k_eps']}, K_max from the sweep = {split['k_max_sweep']}, "
            f"PRDP's final K = {split['k_max_prdp']}") in stdout
    assert f"total {100 * split['total_savings']:.0f}% = IC {100 * split['ic_savings']:.0f}%" in stdout
    assert (f"the solver's iterations are {100 * split['solver_share']:.0f}% of the baseline's time, so PRDP can "
            f"save at most {100 * split['max_wall_time_savings']:.0f}%") in stdout


def test_tradeoff_savings_are_consistent(tradeoff_run):
    report = json.loads((tradeoff_run["out"] / "tradeoff.json").read_text())
    split, runs = report["savings"], report["runs"]
    keps = split["k_eps"]
    assert keps > 2
    assert list(runs) == ["K=1", "K=2", f"K_eps={keps}", "PRDP"]
    assert abs(split["ic_savings"] + split["pr_savings"] - split["total_savings"]) <= 1e-12
    assert split["k_max_sweep"] in (1, 2, keps)
    cost = runs[f"K_eps={keps}"]["total_iterations"]
    k_max_label = f"K={split['k_max_sweep']}" if split["k_max_sweep"] != keps else f"K_eps={keps}"
    assert split["ic_savings"] == pytest.approx(1 - runs[k_max_label]["total_iterations"] / cost, abs=1e-12)
    assert split["total_savings"] == pytest.approx(1 - runs["PRDP"]["total_iterations"] / cost, abs=1e-12)
    assert split["k_max_prdp"] == runs["PRDP"]["rows"][-1]["k"]
    assert split["baseline_final_metric"] == runs[f"K_eps={keps}"]["final_metric"]
    # The epoch override reaches every run and the recorded scene; iteration counts are exact.
    assert report["scene"]["optimizer"]["epochs"] == 4
    for label, k in (("K=1", 1), ("K=2", 2), (f"K_eps={keps}", keps)):
        assert [r["epoch"] for r in runs[label]["rows"]] == [0, 1, 2, 3]
        assert runs[label]["total_iterations"] == 2 * TRAIN * k * 4
    prdp_ks = [r["k"] for r in runs["PRDP"]["rows"]]
    assert runs["PRDP"]["total_iterations"] == 2 * TRAIN * sum(prdp_ks)
    # The per-run directories hold the same rows.
    for label, sub in (("K=1", "k1"), ("K=2", "k2"), (f"K_eps={keps}", "converged"), ("PRDP", "prdp")):
        assert metrics(tradeoff_run["out"] / sub) == runs[label]["rows"]
    # The clock's bound comes from the baseline's own split: its iterations' share of its wall time.
    last = runs[f"K_eps={keps}"]["rows"][-1]
    share = last["time_iterations"] / last["wall_time"]
    assert 0 < share < 1 and split["solver_share"] == pytest.approx(share, rel=1e-12)
    assert split["max_wall_time_savings"] == split["solver_share"]
    assert split["predicted_wall_time_savings"] == pytest.approx(share * split["total_savings"], rel=1e-12)
    assert split["predicted_wall_time_savings"] <= split["max_wall_time_savings"]


def test_tradeoff_csv_matches_json(tradeoff_run):
    report = json.loads((tradeoff_run["out"] / "tradeoff.json").read_text())
    with (tradeoff_run["out"] / "tradeoff.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["run"] for r in rows] == list(report["runs"])
    for row in rows:
        entry = report["runs"][row["run"]]
        assert row["mode"] == entry["mode"]
        assert int(row["total_iterations"]) == entry["total_iterations"]
        assert float(row["final_metric"]) == entry["final_metric"]
    assert {r["mode"] for r in rows} == {"fixed", "converged", "prdp"}


# ------------------------------------------------------------------ sip / hig scenes: run and compare
TINY_SIP = tiny_scene("sip", description="tiny Poisson source inference for the CLI tests",
                      data={"train": 8, "validation": 4}, optimizer={"epochs": 4, "batch": 8})
METHOD_ROW = re.compile(r"^(?P<run>sip|backprop) +(?P<its>[\d,]+) +(?P<metric>\S+e[+-]\d+) +(?P<time>[\d.]+) +"
                        r"(?P<ratio>[\d.]+)x +(?P<per_it>[\d.]+)$")


@pytest.fixture(scope="module")
def tiny_sip(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("sip") / "tiny-sip.toml"
    path.write_text(TINY_SIP)
    return path


def _method_rows(stdout: str) -> dict[str, dict]:
    rows = {}
    for line in stdout.splitlines():
        match = METHOD_ROW.match(line)
        if match:
            rows[match["run"]] = {"its": int(match["its"].replace(",", "")), "metric": float(match["metric"]),
                                  "ratio": float(match["ratio"])}
    return rows


def test_run_on_a_sip_scene_trains_the_method_and_the_baseline(tiny_sip, tmp_path):
    code, stdout, stderr = call(["run", tiny_sip, "--out", tmp_path, "--no-progress"])
    assert code == 0, stderr
    rows = _method_rows(stdout)
    assert set(rows) == {"sip", "backprop"} and rows["sip"]["its"] == rows["backprop"]["its"] == 4
    for name in rows:
        saved = metrics(tmp_path / name)
        assert len(saved) == 4 and rows[name]["metric"] == pytest.approx(saved[-1]["val_metric"], rel=1e-3)
    assert rows["sip"]["ratio"] == pytest.approx(rows["sip"]["metric"] / rows["backprop"]["metric"], abs=1e-3)


def test_compare_writes_the_report_and_prints_both_ratios(tiny_sip, tmp_path):
    code, stdout, stderr = call(["compare", tiny_sip, "--out", tmp_path, "--epochs", "3", "--no-progress"])
    assert code == 0, stderr
    report = json.loads((tmp_path / "compare.json").read_text())
    split = report["summary"]
    assert split["iterations"] == 3 and len(report["runs"]["sip"]["rows"]) == 3
    assert len(report["runs"]["backprop"]["rows"]) >= 3
    assert f"ratio {split['ratio_equal_iterations']:.3f}" in stdout
    if split["ratio_equal_time"] is None:
        # Three epochs last milliseconds: on a loaded machine the baseline's first epoch can
        # outlast the method's whole run, and the report must then say there is no equal-time ratio.
        assert split["baseline_metric_at_equal_time"] is None
        assert "no comparison at equal training time" in stdout
    else:
        assert f"SIP / Adam + backprop = {split['ratio_equal_time']:.3f}" in stdout
    assert (tmp_path / "error_vs_cost.png").read_bytes()[:8] == PNG_SIGNATURE


@pytest.mark.parametrize("argv, fragment", [
    (["run", "{sip}", "--k", "3"], "--k, --prdp, --converged and --parallel choose solver caps"),
    (["run", "{sip}", "--prdp"], "--k, --prdp, --converged and --parallel choose solver caps"),
    (["tradeoff", "{sip}"], "`fempdl tradeoff` does not apply to the sip scene 'tiny-sip'; use `fempdl compare`"),
    (["compare", "{tiny}"], "`fempdl compare` does not apply to the emulator scene 'tiny-emulator'; "
                            "use `fempdl tradeoff`"),
])
def test_method_commands_refuse_what_does_not_apply(argv, fragment, tiny, tiny_sip):
    code, _, stderr = call([a.format(sip=tiny_sip, tiny=tiny) for a in argv])
    assert code == 2 and fragment in stderr


def test_tradeoff_csv_splits_each_runs_wall_time(tradeoff_run):
    """Every run's time parts in tradeoff.csv add up to its wall time."""
    import csv
    with (tradeoff_run["out"] / "tradeoff.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert rows
    for row in rows:
        parts = [float(v) for k, v in row.items() if k.startswith("time_")]
        assert len(parts) == 7 and min(parts) >= -1e-3
        assert sum(parts) == pytest.approx(float(row["wall_time"]), rel=1e-9)


# ------------------------------------------------------------------ --set and scenes --show
def test_scenes_show_prints_the_bundled_toml(capsys):
    assert cli.main(["scenes", "--show", "heat-emulator-2d"]) == 0
    text = capsys.readouterr().out
    assert text == scene.bundled_text("heat-emulator-2d")
    shown = scene.parse(text, source="shown")
    assert dataclasses.replace(shown, source="") == dataclasses.replace(scene.load("heat-emulator-2d"), source="")
    assert cli.main(["scenes", "--show", "no-such-scene"]) == 2
    assert capsys.readouterr().err.startswith("fempdl: unknown scene 'no-such-scene'; bundled scenes are")


def test_scenes_schema_prints_every_section_and_key(capsys):
    assert cli.main(["scenes", "--schema"]) == 0
    text = capsys.readouterr().out
    assert text == scene.schema_text() + "\n"
    headers = [line.split()[0] for line in text.splitlines() if line.startswith("[")]
    assert headers == [f"[{name}]" for name in schema.SECTIONS]
    for name, block in zip(schema.SECTIONS, text.split("\n[")[1:]):
        keys = [line.split()[0] for line in block.splitlines()[1:] if line.strip()]
        assert keys == [field.name for field in dataclasses.fields(schema.SECTIONS[name])], name


def test_set_values_are_toml_or_plain_strings(tiny):
    quoted = scene.load(tiny, ['solver.preset="cg"', "optimizer.lr=2e-3", "prdp.k_cap = 9", "network.hidden=8"])
    plain = scene.load(tiny, ["solver.preset=cg", "optimizer.lr=2e-3", "prdp.k_cap=9", "network.hidden=8"])
    assert quoted == plain
    assert (plain.solver.preset, plain.optimizer.lr, plain.prdp.k_cap, plain.network.hidden) == \
        ("cg", 2e-3, 9, 8)
    assert scene.load(tiny).solver.preset == "jacobi"


def test_run_with_set_trains_the_overridden_scene(tiny, tmp_path):
    code, _, stderr = call(["run", tiny, "--k", "2", "--no-baseline", "--out", tmp_path, "--no-progress",
                            "--set", "optimizer.epochs=2", "--set", "data.train=8"])
    assert code == 0, stderr
    rows = metrics(tmp_path / "k2")
    assert len(rows) == 2 and {row["k"] for row in rows} == {2}
    # 8 training samples (cumulative counts): one forward solve of K=2 per sample and epoch
    assert [row["forward_iterations"] for row in rows] == [8 * 2, 8 * 2 * 2]


@pytest.mark.parametrize("argv, fragment", [
    (["run", "{tiny}", "--set", "optimizer.epochs=five"], "[optimizer] epochs must be of type int, got 'five' (str)"),
    (["run", "{tiny}", "--set", "optimizer.epoch=5"], "unknown key(s) ['epoch'] in [optimizer]"),
    (["tradeoff", "{tiny}", "--set", "solver.preset=direct"], "[solver] preset must be one of"),
    (["compare", "{sip}", "--set", "optimizer=5"], "--set 'optimizer=5' must have the form section.key=value"),
    (["run", "{tiny}", "--set", "nosuch.x=1"], "unknown section(s) ['nosuch']"),
])
def test_set_errors_name_the_key(argv, fragment, tiny, tiny_sip, tmp_path):
    code, stdout, stderr = call([a.format(sip=tiny_sip, tiny=tiny) for a in argv] + ["--out", tmp_path / "o"])
    assert code == 2 and fragment in stderr and stdout == ""
    assert not (tmp_path / "o").exists()


# ------------------------------------------------------------------ logs
EPOCH_LINE = re.compile(r"^fempdl: (?P<run>\S+): epoch (?P<epoch>\d+)/(?P<epochs>\d+) loss \S+ val (?P<val>\S+) "
                        r"K (?P<k>\d+) iterations (?P<its>\d+) wall [\d.]+ s$")


def _epoch_lines(stderr: str) -> list[dict]:
    return [m.groupdict() for m in map(EPOCH_LINE.match, stderr.splitlines()) if m]


@pytest.mark.parametrize("every, logged", [(None, [1, 2, 3, 4]), ("2", [2, 4]), ("3", [3])])
def test_epoch_lines_on_a_non_terminal_stderr(tiny, tmp_path, every, logged):
    code, _, stderr = call(["run", tiny, "--k", "2", "--no-baseline", "--out", tmp_path, "--set", "data.train=8",
                            "--set", "optimizer.epochs=4"] + (["--log-every", every] if every else []))
    assert code == 0, stderr
    lines = _epoch_lines(stderr)
    rows = metrics(tmp_path / "k2")
    assert [int(line["epoch"]) for line in lines] == logged
    for line in lines:
        row = rows[int(line["epoch"]) - 1]
        assert (line["run"], line["epochs"], int(line["k"]), int(line["its"])) == \
            ("k2", "4", 2, row["total_iterations"])
        assert float(line["val"]) == pytest.approx(row["val_metric"], rel=1e-3)


def test_prdp_refinements_and_k_eps_are_logged(default_run):
    stderr = default_run["stderr"]
    keps = metrics(default_run["out"] / "converged")[-1]["k"]
    assert f"fempdl: K_eps = {keps} (richardson + jacobi to rtol " in stderr
    ks = [row["k"] for row in metrics(default_run["out"] / "prdp")]
    changes = [(a, b) for a, b in zip(ks, ks[1:]) if a != b]
    logged = re.findall(r"^fempdl: PRDP: K (\d+) -> (\d+) \((plateau|rise)\) at step \d+, metric \S+$",
                        stderr, flags=re.M)
    # the last epoch's refinement (if any) shows in the log but not in a later row's K
    assert [(int(a), int(b)) for a, b, _ in logged][:len(changes)] == changes
    assert len(_epoch_lines(stderr)) == 2 * EPOCHS            # PRDP and the baseline, every epoch


# ------------------------------------------------------------------ --save-fields
def test_save_fields_writes_predictions_references_and_a_png(tiny, tmp_path):
    code, stdout, stderr = call(["run", tiny, "--k", "2", "--no-baseline", "--out", tmp_path, "--set",
                                 "optimizer.epochs=2", "--save-fields"])
    assert code == 0, stderr
    run_dir = tmp_path / "k2"
    assert (run_dir / "fields.png").read_bytes()[:8] == PNG_SIGNATURE
    assert (run_dir / "fields.h5").read_bytes()[:8] == b"\x89HDF\r\n\x1a\n"
    import xml.etree.ElementTree as ET
    root = ET.parse(run_dir / "fields.xdmf").getroot()
    written = {(a.get("Name"), float(g.find("Time").get("Value")))
               for g in root.iter("Grid") if g.find("Time") is not None for a in g.findall("Attribute")}
    assert written == {(name, float(i)) for name in ("prediction", "reference", "error") for i in range(4)}


def test_validation_fields_are_what_the_metric_measures(tiny):
    import torch

    from fempdl.app.runs import runner
    from fempdl.app.tasks.metrics import sample_nmse
    from fempdl.ksp_adjoint import KSPOptions
    sc = scene.load(tiny)
    assert sc.data.rollout == 1
    task = runner.build_task(sc, KSPOptions(max_it=2))
    try:
        name, prediction, reference = task.validation_fields(torch.arange(task.val_size))
        assert name is None and prediction.shape == reference.shape == (task.val_size, task.problem.output_size)
        assert float(sample_nmse(prediction, reference).mean()) == pytest.approx(task.validate(), rel=1e-5)
    finally:
        task.close()


@pytest.mark.parametrize("argv, fragment", [
    (["run", "{sip}", "--save-fields"], "--save-fields writes the fields of PRDP scenes; the sip scene 'tiny-sip'"),
])
def test_save_fields_refusals(argv, fragment, tiny, tiny_sip, tmp_path):
    code, _, stderr = call([a.format(sip=tiny_sip, tiny=tiny) for a in argv] + ["--out", tmp_path / "o"])
    assert code == 2 and fragment in stderr


# ------------------------------------------------------------------ TensorBoard
def test_run_tensorboard_writes_every_metric_as_scalars(tiny, tmp_path):
    pytest.importorskip("tensorboard", reason="the tensorboard extra is not installed")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    out = tmp_path / "out"
    code, _, stderr = call(["run", tiny, "--k", "2", "--no-baseline", "--tensorboard", "--out", out, "--no-progress"])
    assert code == 0, stderr
    rows = metrics(out / "k2")
    events = EventAccumulator(str(out / "k2" / "tensorboard"))
    events.Reload()
    for key in ("train_loss", "val_metric", "k", "total_iterations", "wall_time", "time_iterations"):
        scalars = events.Scalars(key)
        assert [s.step for s in scalars] == [row["epoch"] + 1 for row in rows]
        assert [s.value for s in scalars] == pytest.approx([float(row[key]) for row in rows], rel=1e-6)


def test_tensorboard_without_the_package_says_how_to_install_it(tiny, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "torch.utils.tensorboard", None)      # import fails as if not installed
    with pytest.raises(ImportError, match=r"pip install 'fempdl\[tensorboard\]'"):
        runner.run(scene.load(tiny), "fixed", 1, out_dir=tmp_path / "out", epochs=1, tensorboard=True)


def test_each_log_line_appears_once_in_a_real_process(tiny, tmp_path):
    """Importing dolfinx installs a stderr handler on the root logger; the command's lines
    must not also go out through it."""
    import subprocess

    done = subprocess.run([sys.executable, "-m", "fempdl.app.cli", "run", str(tiny), "--k", "2", "--no-baseline",
                           "--out", str(tmp_path), "--set", "data.train=8", "--set", "optimizer.epochs=3"],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    assert [int(line["epoch"]) for line in _epoch_lines(done.stderr)] == [1, 2, 3]
    assert "INFO:fempdl" not in done.stderr
