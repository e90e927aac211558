"""The `fempdl run` command: iteration accounting of the default example and argument errors."""
from __future__ import annotations

import re

import pytest

from fempdl import cli, heat_demo


def test_run_reports_exact_iteration_counts(capsys):
    assert cli.main(["run", "--k", "3", "--epochs", "2", "--no-baseline", "--no-progress"]) == 0
    out = capsys.readouterr().out
    # 64 training samples x 2 epochs x K=3, forward and backward.
    samples = heat_demo.HeatDemoConfig().train_samples * 2
    row = next(line for line in out.splitlines() if line.split() and line.split()[0] == "3")
    assert f"{2 * samples * 3:,d}" in row
    nmse = float(row.split()[3])
    assert 0 < nmse < 10


def test_capped_training_beats_the_untrained_network_at_a_sufficient_cap():
    result = heat_demo.run(heat_demo.HeatDemoConfig(k=16, epochs=10), progress=False)
    assert result.val_nmse < 0.5 * result.val_nmse_untrained
    assert result.forward_iterations == 10 * 64 * 16 == result.backward_iterations
    assert result.converged_iterations_per_solve > 16


@pytest.mark.parametrize("bad", ["0", "x", "3,-1"])
def test_bad_k_is_rejected(bad, capsys):
    with pytest.raises(SystemExit):
        cli.main(["run", "--k", bad])
    assert re.search(r"--k", capsys.readouterr().err)
