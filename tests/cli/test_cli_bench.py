"""`roadgrip bench estimate` on the command line (roadgrip/cli/bench.py): channel sets and their rows."""

import pytest
from typer.testing import CliRunner

from roadgrip.cli import app

runner = CliRunner()


@pytest.mark.slow
def test_bench_estimate_prints_a_row_per_channel_set_and_refuses_an_unknown_one():
    result = runner.invoke(
        app, ["bench", "estimate", "--estimator", "ekf", "--channel-set", "gnss", "--channels", "--updates", "100"]
    )
    assert result.exit_code == 0, result.output
    assert "| ekf [gnss] |" in result.output and "| ekf [all] |" in result.output  # brackets printed, not markup
    result = runner.invoke(app, ["bench", "estimate", "--estimator", "ekf", "--channel-set", "radar"])
    assert result.exit_code != 0
    assert "unknown channel set 'radar'" in result.output
