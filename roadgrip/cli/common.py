"""What every command shares: the console it prints on and `friendly_errors`, which turns bad input into exit status 2."""

from __future__ import annotations

import functools

import typer
from rich.console import Console

console = Console()


def friendly_errors(fn):
    """Bad input ends the command with its message and exit status 2, not a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (ValueError, TypeError, FileExistsError, FileNotFoundError) as err:
            console.print(f"[bold red]error:[/] {err}")
            raise typer.Exit(2) from err

    return wrapper
