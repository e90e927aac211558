"""Run under mpirun (any number of ranks, 1 included): a tiny scene trained with
``parallel=argv[1]`` ("data": the heat emulator, "mesh": the Poisson inverse, "mesh-warm": it
with warm-started solves). Rank 0 writes to the JSON file argv[2]: the metric rows of a full
run, those of a run stopped after 3 epochs and resumed, the K schedule every
rank saw, and the message of a deliberately failed agreement check."""
from __future__ import annotations

import json
import sys
import tempfile
from pathlib import Path

from mpi4py import MPI

from fempdl.app import scene
from fempdl.app.runs import runner
from fempdl.core import parallel

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))   # tests/, for helpers
from helpers import tiny_scene  # noqa: E402

parallel.abort_on_error()

# The emulator's last batch of 1 (17 samples in batches of 8) leaves a rank without samples.
EMULATOR = tiny_scene(name="tiny-heat-parallel", data={"train": 17, "validation": 5}, optimizer={"epochs": 8},
                      prdp={"ema_window": 1})
INVERSE_EDITS = {"scene": {"name": "tiny-inverse-parallel"}, "mesh": {"h": 0.1}, "optimizer": {"epochs": 8},
                 "prdp": {"k0": 5, "dk": 5, "tau_step": 0.95, "delta": 2, "ema_window": 1}}
SCENES = {"data": EMULATOR, "mesh": tiny_scene("inverse", INVERSE_EDITS),
          # "mesh-warm": the inverse with warm-started solves, whose last solution each rank keeps and saves.
          "mesh-warm": tiny_scene("inverse", INVERSE_EDITS, solver={"warm_start": True})}

mode, out = sys.argv[1], Path(sys.argv[2])
comm = MPI.COMM_WORLD
sc = scene.parse(SCENES[mode])
with tempfile.TemporaryDirectory() as tmp:
    run_dir = Path(comm.bcast(tmp if comm.rank == 0 else None))   # one directory, seen by every rank
    parallel_mode = mode.partition("-")[0]
    full = runner.run(sc, "prdp", parallel=parallel_mode)
    runner.run(sc, "prdp", parallel=parallel_mode, out_dir=run_dir, stop_after=3, k_eps_value=full.k_eps)
    resumed = runner.run(sc, "prdp", parallel=parallel_mode, out_dir=run_dir, resume=True, k_eps_value=full.k_eps)
    written = json.loads((run_dir / "metrics.json").read_text()) if comm.rank == 0 else None
    comm.barrier()   # every rank is done with the directory before rank 0 removes it
try:
    parallel.check_identical(comm, value=comm.rank)
    message = ""
except RuntimeError as err:
    message = str(err)
ks_by_rank = comm.gather([row["k"] for row in full.rows])
if comm.rank == 0:
    out.write_text(json.dumps({"rows": full.rows, "resumed_rows": resumed.rows, "written_rows": written,
                               "k_eps": full.k_eps, "ks_by_rank": ks_by_rank, "check_message": message,
                               "ranks": comm.size}))
