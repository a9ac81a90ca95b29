"""The command table (roadgrip/cli/__init__.py) and what the commands share (roadgrip/cli/common.py)."""

import subprocess
import sys

import click
import pytest
import typer
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cli.common import friendly_errors

runner = CliRunner()


def test_the_commands_are_listed_in_their_order():
    group = typer.main.get_command(app)
    ctx = click.Context(group)
    assert group.list_commands(ctx) == [
        "simulate",
        "train",
        "evaluate",
        "estimate",
        "fleet",
        "import-log",
        "serve",
        "worker",
        "api",
        "demo",
        "edge",
        "bench",
        "cluster",
    ]
    assert group.get_command(ctx, "bench").list_commands(ctx) == [
        "estimate",
        "ingest",
        "cluster",
        "failover",
        "sim",
        "uplink",
    ]
    assert group.get_command(ctx, "cluster").list_commands(ctx) == ["up"]


def test_help_imports_neither_torch_nor_the_cloud():
    """`roadgrip --help` stays fast: the heavy parts are imported inside the commands that use them."""
    code = (
        "import sys\n"
        "from roadgrip.cli import app\n"
        "try:\n"
        "    app(['--help'], prog_name='roadgrip')\n"
        "except SystemExit as exit:\n"
        "    assert exit.code == 0, exit.code\n"
        "print(' '.join(sorted(sys.modules)))\n"
    )
    modules = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=120
    ).stdout.split()
    assert "roadgrip.cli.data" in modules  # the list is the real one
    heavy = (
        "torch",
        "uvicorn",
        "fastapi",
        "roadgrip.cloud",
        "roadgrip.fleet",
        "roadgrip.training",
        "roadgrip.evaluation",
        "roadgrip.bench",
        "roadgrip.estimators",
    )
    assert [m for m in modules if m.startswith(heavy)] == []


def _command(error: Exception):
    cli = typer.Typer()

    @cli.command()
    @friendly_errors
    def fail(value: int = typer.Option(0, help="a value")):
        """Raise the error."""
        raise error

    return cli


@pytest.mark.parametrize(
    "error",
    [
        ValueError("--value must be positive, got -1"),
        TypeError("--value must be an int"),
        FileExistsError("out exists"),
        FileNotFoundError("no such file: in.csv"),
    ],
)
def test_bad_input_ends_with_its_message_and_status_2(error):
    result = runner.invoke(_command(error), [])
    assert result.exit_code == 2
    assert f"error: {error}" in result.output


def test_other_errors_are_not_hidden():
    result = runner.invoke(_command(RuntimeError("a bug")), [])
    assert result.exit_code == 1 and isinstance(result.exception, RuntimeError)
