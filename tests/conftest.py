"""Shared by every test: the helper modules' folders on sys.path.

The helpers (tests/fake_clock.py; tests/cloud/drives.py, service_fixtures.py, broker_fixtures.py, ...) are plain
modules, imported by name (`from drives import patch_drive`). pytest puts a test's own folder on sys.path only when it
collects that test, so a helper of another folder imported only because some earlier test's folder was there: here
tests/ and tests/cloud/ are on it before any test module is imported, whichever runs first, alone or in the suite.
No test module imports another test module.
"""

from __future__ import annotations

import sys
from pathlib import Path

TESTS = Path(__file__).resolve().parent

for folder in (TESTS, TESTS / "cloud"):
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
