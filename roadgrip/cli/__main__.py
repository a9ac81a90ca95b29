"""`python -m roadgrip.cli` is the `roadgrip` command."""

from roadgrip.cli import app

app(prog_name="roadgrip")
