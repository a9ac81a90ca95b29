"""Shared by every test: the helper modules' folders on sys.path.

The helpers (tests/fake_clock.py; tests/cloud/drives.py, service_fixtures.py, broker_fixtures.py, ...;
tests/data/telemetry_samples.py; tests/estimators/contract_drives.py) are plain modules, imported by name (`from drives
import patch_drive`). Tests are imported with `--import-mode=importlib` (pyproject.toml), so that test modules may share
a name in different folders as the package's modules do (tests/bench/test_checkpoints.py,
tests/cloud/pipeline/test_checkpoints.py); that mode puts no test folder on sys.path, so every folder holding a helper
is put there here, before any test module is imported. No test module imports another test module.
"""

from __future__ import annotations

import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

HELPER_FOLDERS = sorted(
    {p.parent for p in TESTS.rglob("*.py") if not p.name.startswith("test_") and p.name != "conftest.py"}
)

for folder in HELPER_FOLDERS:
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))


def pytest_configure(config):
    """Under pytest-xdist, before its workers start: compile numba's kernels once (the simulator's, and pmf's, the
    EKF's and the UKF's batch and streaming paths) into numba's cache, which each worker then loads. On a fresh clone
    every worker would otherwise compile them itself, about a minute each on a busy machine (README)."""
    if hasattr(config, "workerinput") or not config.getoption("numprocesses", default=None):
        return
    import numpy as np

    from roadgrip.cloud.process import warm_up
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.sim.presets import paper_scenarios
    from roadgrip.sim.simulate import simulate

    scenario = paper_scenarios()[0]
    table = simulate([scenario]).slice(0, 100)
    for name in ("pmf", "ekf", "ukf"):
        estimator = load_estimator(name)
        estimator.estimate_batch(table, np.zeros(table.num_rows, dtype=np.int64), scenario.vehicle)
        warm_up(estimator)
