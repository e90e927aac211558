"""Time CI's part for one stack on a fresh clone: the environment build and the whole suite.

Clones the repository's committed HEAD into a temporary directory and runs
``make setup STACK=...`` and then ``make test STACK=...`` there, as CI does
(CI=true, as root), with an empty cache directory (XDG_CACHE_HOME: no pip
cache, no FFCx form cache) and ``PIP_NO_CACHE_DIR=1``, so every package is
downloaded and every form compiled. Records the seconds of each phase, the
exit codes, pytest's summary line and the machine's load before and after.

Writes ``bench-results/fresh_clone_<stack>.json`` (``--out``).
Run: ``python3 tools/time_fresh_clone.py --stack pypi`` (about 8 minutes on
2 cores; the PyPI venv is about 5 GB). Uses only the standard library.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def run(command: list[str], cwd: Path, env: dict) -> tuple[float, int, str]:
    t0 = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, env=env, capture_output=True, text=True)
    return time.perf_counter() - t0, done.returncode, done.stdout + done.stderr


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--stack", choices=("debian", "pypi"), default="pypi")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    out = args.out or ROOT / "bench-results" / f"fresh_clone_{args.stack}.json"
    commit = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                            check=True).stdout.strip()
    load_before = os.getloadavg()
    started = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    with tempfile.TemporaryDirectory() as tmp:
        clone, cache = Path(tmp) / "clone", Path(tmp) / "cache"
        subprocess.run(["git", "clone", "-q", str(ROOT), str(clone)], check=True)
        env = {**os.environ, "CI": "true", "XDG_CACHE_HOME": str(cache), "PIP_NO_CACHE_DIR": "1",
               "OMP_WAIT_POLICY": "PASSIVE", "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
        setup_s, setup_rc, setup_log = run(["make", "setup", f"STACK={args.stack}"], clone, env)
        test_s, test_rc, test_log = run(["make", "test", f"STACK={args.stack}"], clone, env)
    summary = next((line for line in reversed(test_log.splitlines()) if " in " in line and "passed" in line), "")
    # The benchmark harness's top-level keys (benchmarks/bench_common.py), without its FE-stack machine record:
    # this runs on the machine's own Python, before any venv exists.
    report = {"benchmark": "time_fresh_clone", "date": started, "commit": commit,
              "machine": {"cpu_count": os.cpu_count(), "platform": platform.platform()},
              "load": {"start": list(load_before), "end": list(os.getloadavg())}, "statistic": None, "repeats": None,
              "stack": args.stack,
              "setup_seconds": setup_s, "setup_exit": setup_rc, "test_seconds": test_s, "test_exit": test_rc,
              "total_seconds": setup_s + test_s, "pytest_summary": summary.strip("= ")}
    if setup_rc or test_rc:
        report["log_tail"] = (setup_log if setup_rc else test_log)[-3000:]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(report, indent=2))
    print(json.dumps({k: v for k, v in report.items() if k != "log_tail"}, indent=2))
    print(f"wrote {out}")
    return 0 if not (setup_rc or test_rc) else 1


if __name__ == "__main__":
    sys.exit(main())
