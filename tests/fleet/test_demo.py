"""`roadgrip demo`, the main job, as a user runs it: it must end by itself, print its summary with a warning on a
slippery patch, and leave nothing running."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def mosquitto_pids(under: Path) -> set[int]:
    """The Mosquitto processes configured from a directory below `under` (the demo's own, not another test's)."""
    pids = set()
    for p in Path("/proc").iterdir():
        try:
            mosquitto = p.name.isdigit() and (p / "comm").read_text().strip() == "mosquitto"
            if mosquitto and str(under) in (p / "cmdline").read_bytes().decode(errors="replace"):
                pids.add(int(p.name))
        except OSError:  # exited while listed
            continue
    return pids


@pytest.mark.slow
def test_the_demo_runs_end_to_end_and_leaves_nothing_behind(tmp_path):
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "roadgrip",
            "demo",
            "--vehicles",
            "8",
            "--speed",
            "20",
            "--duration",
            "80",
            "--data-dir",
            str(tmp_path),
        ],
        check=False,
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "COLUMNS": "200"},
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    out = " ".join(result.stdout.split())  # rich wraps titles to the table's width
    assert "roadgrip demo: 8 vehicles over MQTT" in out
    assert "dashboard: http://127.0.0.1:" in out
    assert "slippery-road warnings (0)" not in out, out[-3000:]
    assert "low friction" in out and "ice-expressway" in out
    assert list(tmp_path.rglob("mosquitto.conf")), "the demo started no broker of its own"
    assert mosquitto_pids(tmp_path) == set()
