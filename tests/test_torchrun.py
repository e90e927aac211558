"""torchrun + DistributedDataParallel (gloo, 2 processes, each with the whole mesh): PRDP and the layers
agree over the torch.distributed group, which the mesh's communicator (one process) cannot see.

Before, two ranks stepping PRDP on their own metrics trained at caps 20 and 22 after 40 epochs with no
error, while DDP kept their parameters equal."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).parent.parent
ENV = {**os.environ, "OMP_NUM_THREADS": "1", "OMP_WAIT_POLICY": "PASSIVE"}


def torchrun(script: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
               str(script), *args]
    return subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=300, cwd=cwd)


def lines(done: subprocess.CompletedProcess) -> dict:
    """Each rank's JSON object from the shared stdout (one object per rank, in any order)."""
    decoder, found, text = json.JSONDecoder(), {}, done.stdout
    start = text.find('{"rank"')
    while start >= 0:
        entry, end = decoder.raw_decode(text, start)
        found[entry["rank"]] = entry
        start = text.find('{"rank"', end)
    return found


def test_ddp_example_refines_on_every_rank_together(tmp_path):
    done = torchrun(ROOT / "examples" / "ddp_prdp_loop.py", "--epochs", "12", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    ranks = lines(done)
    assert set(ranks) == {0, 1}
    assert ranks[0]["ks"] == ranks[1]["ks"] and ranks[0]["k"] > 1      # refined, and together
    assert ranks[0]["metric"] == ranks[1]["metric"]


def test_per_rank_metrics_are_refused_on_every_rank(tmp_path):
    done = torchrun(ROOT / "examples" / "ddp_prdp_loop.py", "--epochs", "2", "--local-metric", cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    ranks = lines(done)
    for rank in (0, 1):
        assert "PRDP.step got different metrics on the 2 ranks" in ranks[rank]["error"]
        assert "of its torch.distributed process group" in ranks[rank]["error"]


def test_layers_refuse_training_at_drifted_caps(tmp_path):
    out = tmp_path / "caps"
    done = torchrun(ROOT / "tests" / "mpi" / "torch_caps.py", str(out), cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    seen = [json.loads(Path(f"{out}.rank{r}.json").read_text()) for r in range(2)]
    assert seen[0]["rank0_alone"] > 0                    # a no-grad call on one rank does not wait for the other
    for rank in seen:
        assert "train this SolveLayer at different caps ([Caps(max_it=5), Caps(max_it=6)], by rank)" in rank["layer"]
        assert "NonlinearSolveLayer at different caps ([Caps(max_it=4), Caps(max_it=5)], by rank)" in rank["newton"]
        assert rank["agreed"] == seen[0]["agreed"] > 0
    # rank 0's garbage solve refined both ranks' caps together (rank 1's own solves were healthy at K = 1)
    assert seen[0]["health_k"] == seen[1]["health_k"] > 1
    assert seen[0]["health_refinements"] == seen[1]["health_refinements"] == seen[0]["health_k"] - 1
    for rank in seen:
        assert rank["ranks"] == "Ranks(default torch.distributed process group, backend gloo, size 2)"
        assert "PRDP.step ran on some ranks of the torch.distributed group only (steps by rank: [1, 0])" \
            in rank["step_alone"]
        assert rank["stepped_together"] == seen[0]["stepped_together"]
