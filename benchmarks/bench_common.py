"""The benchmark harness: standard options, timed repeats, and the JSON report every benchmark writes.

Every benchmark builds its parser with :func:`parser` (``--repeats``, ``--out``, ``--quick``), times
with :func:`timed` or :func:`interleaved` (warm-up runs, then ``repeats`` timed runs reduced by one
named statistic), and writes its figures inside :func:`report`. Each JSON file then has the same
top-level keys, :data:`REPORT_KEYS`, beside the benchmark's own results:

- ``"benchmark"``: the script's name; ``"date"``: when it started (UTC);
- ``"machine"``: :func:`machine_info` (CPU, memory, versions, torch threads, OpenMP wait policy);
- ``"load"``: the 1/5/15-minute load averages, ``{"start": [...], "end": [...]}``, and ``"during"``
  (a list of ``{"at": label, "load": [...]}``) where a benchmark samples it between measurements;
- ``"statistic"``: how repeated samples become one figure (:data:`STATISTICS`; null if none);
- ``"repeats"``: timed runs per figure (null if nothing is timed repeatedly).
"""
from __future__ import annotations

import argparse
import contextlib
import datetime
import json
import os
import platform
import statistics as stats
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

# Before anything loads an OpenMP runtime: spinning threads would stall the other
# process of a paired measurement (fempdl's __init__ sets the same default).
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# The FE stack (mpi4py, DOLFINx, PETSc, torch, fempdl) is imported where it is used: worker processes
# that measure their own memory or start-up import this module without paying for it.

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "bench-results"
QUICK_RESULTS = Path(tempfile.gettempdir()) / "fempdl-bench-quick"
#: Named statistics over repeated samples. "min" is the default: other processes only ever add time,
#: so the fastest run is the one least disturbed by them.
STATISTICS: dict[str, Callable] = {"min": min, "median": stats.median, "mean": stats.fmean}
DEFAULT_STATISTIC = "min"
REPORT_KEYS = ("benchmark", "date", "machine", "load", "statistic", "repeats")


def machine_info() -> dict:
    """The machine and software the figures were measured with (the load is in the report's "load")."""
    from mpi4py import MPI  # before DOLFINx: PyPI's DOLFINx needs the MPI library mpi4py loads
    import dolfinx
    import numpy as np
    import petsc4py
    import torch
    from petsc4py import PETSc

    import fempdl
    from fempdl.core import _dolfinx

    meminfo = {}
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                key, value = line.split(":", 1)
                if key in ("MemTotal", "MemAvailable"):
                    meminfo[key] = int(value.split()[0]) / 1024.0 / 1024.0
    except OSError:
        pass
    return {
        "cpu_count": os.cpu_count(),
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "memory_total_gib": meminfo.get("MemTotal"),
        "memory_available_gib_at_start": meminfo.get("MemAvailable"),
        "python": platform.python_version(),
        "torch": torch.__version__,
        "torch_num_threads": torch.get_num_threads(),
        "omp_wait_policy": os.environ.get("OMP_WAIT_POLICY", "runtime default"),
        "stack": _dolfinx.STACK,
        "dolfinx": dolfinx.__version__,
        "petsc": ".".join(map(str, PETSc.Sys.getVersion())),
        "petsc4py": petsc4py.__version__,
        "numpy": np.__version__,
        "fempdl": fempdl.__version__,
        "mpi_ranks": MPI.COMM_WORLD.size,
    }


def load_average() -> list[float]:
    return list(os.getloadavg())


def default_out(script: str | Path, suffix: str = "") -> Path:
    """``bench-results/<script name><suffix>.json``: where a benchmark writes unless given ``--out``."""
    return RESULTS / f"{Path(script).stem}{suffix}.json"


class _Parser(argparse.ArgumentParser):
    """Fills ``--repeats`` left unset: ``quick_repeats`` with ``--quick``, else ``default_repeats``; a
    ``--quick`` run without ``--out`` writes under :data:`QUICK_RESULTS`."""

    default_repeats: int | None = None
    quick_repeats: int | None = None

    def parse_args(self, args=None, namespace=None):
        parsed = super().parse_args(args, namespace)
        if parsed.quick and parsed.out == self.get_default("out"):
            parsed.out = QUICK_RESULTS / parsed.out.name       # a smoke test leaves the committed JSON alone
        if getattr(parsed, "repeats", 0) is None:
            parsed.repeats = self.quick_repeats if parsed.quick and self.quick_repeats else self.default_repeats
        return parsed


def parser(script: str | Path, description: str | None, *, repeats: int | None, quick: str,
           quick_repeats: int | None = None, out_suffix: str = "") -> argparse.ArgumentParser:
    """An argument parser with the standard options: ``--repeats`` (timed runs per figure: ``repeats``,
    or ``quick_repeats`` with ``--quick`` unless given; no such option if ``repeats`` is None, for a
    benchmark that times nothing repeatedly), ``--out`` (default :func:`default_out`) and ``--quick``
    (``quick`` says what the small, fast configuration runs; without ``--out`` its JSON goes to
    :data:`QUICK_RESULTS`, not over the committed one)."""
    p = _Parser(description=description, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.default_repeats, p.quick_repeats = repeats, quick_repeats
    if repeats is not None:
        quick_note = f"; {quick_repeats} with --quick" if quick_repeats else ""
        p.add_argument("--repeats", type=positive_int, default=None,
                       help=f"timed runs per figure after the warm-up (default {repeats}{quick_note})")
    p.add_argument("--out", type=Path, default=default_out(script, out_suffix),
                   help="the JSON file to write (default: %(default)s; with --quick, the same name "
                        f"in {QUICK_RESULTS})")
    p.add_argument("--quick", action="store_true", help=f"a small, fast configuration: {quick}")
    return p


def positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def reduce(samples, statistic: str = DEFAULT_STATISTIC) -> float:
    """One figure from repeated samples, by a named statistic of :data:`STATISTICS`."""
    if statistic not in STATISTICS:
        raise ValueError(f"statistic={statistic!r}: choose one of {sorted(STATISTICS)}")
    return float(STATISTICS[statistic](list(samples)))


@dataclass(frozen=True)
class Timing:
    """Repeated samples of one measurement (seconds) and the figure the statistic makes of them."""
    seconds: float
    samples: tuple[float, ...]
    statistic: str

    def as_dict(self) -> dict:
        return {"seconds": self.seconds, "samples": list(self.samples), "statistic": self.statistic}


def _run(fn: Callable[[], float | None]) -> float:
    """Seconds of one call: what ``fn`` returns if it is a number (its own measure), else its wall time."""
    t0 = time.perf_counter()
    own = fn()
    wall = time.perf_counter() - t0
    return float(own) if isinstance(own, (int, float)) else wall


def slowest_rank(fn: Callable[[], object], comm=None) -> Callable[[], float]:
    """A measurement for :func:`timed` under MPI: all ranks start together; the slowest rank's seconds
    (``comm``: COMM_WORLD by default)."""
    from mpi4py import MPI
    comm = comm or MPI.COMM_WORLD

    def run() -> float:
        comm.barrier()
        t0 = time.perf_counter()
        fn()
        return comm.allreduce(time.perf_counter() - t0, op=MPI.MAX)
    return run


def timed(fn: Callable[[], float | None], *, repeats: int, warmup: int = 1,
          statistic: str = DEFAULT_STATISTIC, report: Report | None = None) -> Timing:
    """Call ``fn`` ``warmup`` times untimed, then ``repeats`` times timed. ``fn`` may return its own
    seconds (a layer's stats, a worker's report); otherwise its wall time counts."""
    return interleaved({"": fn}, repeats=repeats, warmup=warmup, statistic=statistic, report=report)[""]


def interleaved(fns: Mapping[str, Callable[[], float | None]], *, repeats: int, warmup: int = 1,
                statistic: str = DEFAULT_STATISTIC, alternate: bool = False, min_time: float = 0.0,
                min_time_of: str | None = None, max_repeats: int | None = None,
                report: Report | None = None) -> dict[str, Timing]:
    """Time several measurements in alternation (one run of each per round, ``repeats`` rounds after
    ``warmup`` untimed rounds), so that a change of load affects them alike. ``alternate``: every other
    round runs them in reverse order; ``min_time``: more rounds (up to ``max_repeats``) while the timed
    samples (of all measurements, or of ``min_time_of`` alone) add up to less; ``report``: its load is
    sampled after every timed round."""
    if repeats < 1 or warmup < 0:
        raise ValueError(f"repeats must be >= 1 and warmup >= 0, got repeats={repeats}, warmup={warmup}")
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    samples: dict[str, list[float]] = {name: [] for name in fns}
    counted = [samples[min_time_of]] if min_time_of is not None else list(samples.values())
    i = 0
    while i < repeats or (sum(map(sum, counted)) < min_time and i < (max_repeats or repeats)):
        order = list(fns.items())
        for name, fn in (order[::-1] if alternate and i % 2 else order):
            samples[name].append(_run(fn))
        i += 1
        if report is not None:
            report.sample_load(f"after round {i}")
    return {name: Timing(reduce(s, statistic), tuple(s), statistic) for name, s in samples.items()}


def pick(runs: list[dict], key: str, statistic: str = DEFAULT_STATISTIC) -> dict:
    """The run whose ``key`` the statistic selects (the fastest for "min", the lower median for
    "median"), with ``key`` set to the statistic and the samples added as ``<key>_samples``."""
    values = [r[key] for r in runs]
    figure = reduce(values, statistic)
    chosen = min(runs, key=lambda r: abs(r[key] - figure))
    return {**chosen, key: figure, f"{key}_samples": values}


def repeat_runs(fn: Callable[[], dict], key: str, *, repeats: int, warmup: int = 0,
                statistic: str = DEFAULT_STATISTIC) -> dict:
    """Call ``fn`` (one run, returning a record with its seconds under ``key``) ``warmup`` times untimed
    and ``repeats`` times; the record :func:`pick` selects, or the first without ``key`` (a failure)."""
    for _ in range(warmup):
        fn()
    runs = [fn() for _ in range(repeats)]
    failed = [r for r in runs if key not in r]
    return failed[0] if failed else pick(runs, key, statistic)


class Report(dict):
    """The JSON a benchmark writes: :data:`REPORT_KEYS` plus its own results (set them as items)."""

    def __init__(self, script: str | Path, out: Path, *, statistic: str | None, repeats: int | None, **results):
        if statistic is not None and statistic not in STATISTICS:
            raise ValueError(f"statistic={statistic!r}: choose one of {sorted(STATISTICS)}")
        super().__init__(benchmark=Path(script).stem,
                         date=datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
                         machine=machine_info(), load={"start": load_average(), "end": None},
                         statistic=statistic, repeats=repeats)
        self.update(results)
        self.out = Path(out)

    def sample_load(self, at: str) -> None:
        """Record the load average now, between measurements, under ``load["during"]``."""
        self["load"].setdefault("during", []).append({"at": at, "load": load_average()})

    def save(self) -> None:
        """Write the JSON now (benchmarks that save after every run); the end load is the current one."""
        self["load"]["end"] = load_average()
        write_json_atomically(dict(self), self.out)


@contextlib.contextmanager
def report(script: str | Path, out: Path, *, statistic: str | None = DEFAULT_STATISTIC, repeats: int | None,
           **results) -> Iterator[Report]:
    """Record the machine and the load at the start; on leaving the block without an error, the load at
    the end, and write the JSON to ``out`` (only rank 0 of an MPI job writes). ``statistic`` and
    ``repeats`` say how the figures were made (both None: nothing was timed repeatedly; "mean" with
    ``repeats=1``: single runs averaged over seeds)."""
    from mpi4py import MPI
    rep = Report(script, out, statistic=statistic, repeats=repeats, **results)
    yield rep
    if MPI.COMM_WORLD.rank == 0:
        rep.save()
        print(f"wrote {rep.out}", file=sys.stderr)


def write_json_atomically(data: dict, path: Path) -> None:
    from fempdl.app.runs.training import write_atomically
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomically(path, lambda p: p.write_text(json.dumps(data, indent=2)))


def run_mpi_worker(script, ranks: int, worker_args: list, out: Path) -> dict:
    """Run ``script`` with ``worker_args`` under ``mpirun -n ranks`` (root allowed) and read the
    JSON its rank 0 wrote to ``out``; a failed job raises with the end of its stderr."""
    from fempdl.core import _dolfinx
    command = [*_dolfinx.mpi_launcher(), "-n", str(ranks), sys.executable, str(script), *map(str, worker_args)]
    env = {**os.environ, "OMPI_ALLOW_RUN_AS_ROOT": "1", "OMPI_ALLOW_RUN_AS_ROOT_CONFIRM": "1"}
    done = subprocess.run(command, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    return json.loads(Path(out).read_text())


def comma_list(kind):
    def parse(text: str) -> list:
        return [kind(item) for item in text.split(",") if item]
    return parse


def apply_defaults(parser, args, defaults: dict, mesh_sizes, solvers) -> None:
    """Fill the options left unset from ``defaults`` and check --sizes, --solvers and --ks."""
    for key, value in defaults.items():
        if getattr(args, key) is None:
            setattr(args, key, value)
    for size in args.sizes:
        if size not in mesh_sizes:
            parser.error(f"--sizes: unknown size {size!r}; choose from {sorted(mesh_sizes)}")
    for name in args.solvers:
        if name not in solvers:
            parser.error(f"--solvers: unknown solver {name!r}; choose from {sorted(solvers)}")
    if not args.ks or min(args.ks) < 1:
        parser.error(f"--ks must be integers >= 1, got {args.ks}")
