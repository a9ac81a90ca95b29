"""`roadgrip demo`, the main job, as a user runs it: it must end by itself, print its summary with a warning on a
slippery patch, and leave nothing running."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest


def mosquitto_pids() -> set[int]:
    return {
        int(p.name)
        for p in Path("/proc").iterdir()
        if p.name.isdigit() and (p / "comm").exists() and (p / "comm").read_text().strip() == "mosquitto"
    }


@pytest.mark.slow
def test_the_demo_runs_end_to_end_and_leaves_nothing_behind(tmp_path):
    before = mosquitto_pids()
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
    assert mosquitto_pids() <= before
