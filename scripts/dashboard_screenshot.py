"""Write docs/dashboard.png: the live dashboard as headless Chromium shows it at 1280x800, on a service loaded with the
drives of tests/cloud/api/test_dashboard.py (two vehicles braking on a slippery patch raise a warning, a third on the dry
road). No base map (no tile server configured): the page makes no request outside the local service.

    python scripts/dashboard_screenshot.py [--out docs/dashboard.png]

Needs the test extras (pytest) and Chromium (`bash scripts/install_system_deps.sh`).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "cloud"))  # the drives and the dashboard tests' set-up

from dashboard_fixtures import (
    CHOSEN,
    READER,
    dashboard_settings,
    load_patch_drives,
    run_chromium,
    serving,
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "dashboard.png", help="PNG to write")
    args = parser.parse_args()
    out = args.out.resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    with (
        tempfile.TemporaryDirectory(prefix="roadgrip-screenshot-") as data_dir,
        serving(dashboard_settings(Path(data_dir))) as (service, base_url),
    ):
        secret = load_patch_drives(service, base_url)
        run_chromium(
            f"{base_url}/dashboard?vehicle={CHOSEN}#{READER}:{secret}",
            f"--screenshot={out}",
            "--window-size=1280,800",
            "--hide-scrollbars",
        )
    if not out.is_file():
        sys.exit(f"chromium wrote no screenshot to {out}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
