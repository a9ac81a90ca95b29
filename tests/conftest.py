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
