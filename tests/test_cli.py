import json

from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.data.dataset import read_dataset

runner = CliRunner()


def test_simulate_writes_a_dataset_and_is_reproducible(tmp_path):
    for name in ("a", "b"):
        result = runner.invoke(app, ["simulate", "--preset", "random", "--runs", "3", "--seed", "7",
                                     "--out", str(tmp_path / name)])
        assert result.exit_code == 0, result.output
    assert read_dataset(tmp_path / "a").equals(read_dataset(tmp_path / "b"))
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["preset"] == "random" and manifest["seed"] == 7 and manifest["runs"] == 3
    assert manifest["rows"] == 3 * 400 and len(manifest["scenarios"]) == 3


def test_bad_input_is_a_clear_error_and_writes_nothing(tmp_path):
    result = runner.invoke(app, ["simulate", "--preset", "carsim", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert "preset" in result.output and "'carsim'" in result.output
    assert not (tmp_path / "x").exists()


def test_demo_runs_end_to_end(tmp_path):
    result = runner.invoke(app, ["demo", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert (tmp_path / "paper-decreasing-straight-e1.png").stat().st_size > 10_000
    assert read_dataset(tmp_path / "paper-dataset").num_rows == 8000
