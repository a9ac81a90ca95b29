"""Replay the estimates a `roadgrip demo` stored (its SQLite database, in the folder its "cloud log" line names) through
the warning engine of the code on PYTHONPATH, in 1 s rounds on the data clock, and print every event: whether a
difference between two demo runs comes from the engine's rules or from the live service's batching
(docs/RESULTS.md, "Warnings that last: the last two misses").

    PYTHONPATH=. python results/trials/results/demo_replay.py /tmp/roadgrip-demo-XXXX/roadgrip.sqlite
"""

from __future__ import annotations

import argparse
import bisect
import sqlite3
from pathlib import Path

from roadgrip.cloud.domain.warnings import WarningEngine


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("database", type=Path, help="a demo's roadgrip.sqlite")
    args = parser.parse_args()
    if not args.database.is_file():
        raise SystemExit(f"no database at {args.database}")
    db = sqlite3.connect(args.database)
    db.row_factory = sqlite3.Row
    rows = [{**dict(r), "excited": bool(r["excited"])} for r in db.execute("SELECT * FROM estimates ORDER BY 2")]
    if not rows:
        raise SystemExit(f"no estimates in {args.database}")
    engine, start_ms = WarningEngine(), rows[0]["timestamp_ms"]
    times = [r["timestamp_ms"] for r in rows]
    events, i = [], 0
    for now_ms in range(start_ms + 1000, times[-1] + 2001, 1000):  # 1 s rounds, then one to close the last passes
        j = bisect.bisect_left(times, now_ms)
        events += engine.update(rows[i:j], now_ms)
        i = j
    for e in events:
        print(
            f"{e.cell} {e.status} {e.reason}: detected {(e.detection_ms - start_ms) / 1000:.1f} s, evidence "
            f"{(e.evidence_ms - start_ms) / 1000:.1f} s, mu_upper {e.mu_upper:.2f}, {e.n_passes} passes, "
            f"{e.n_vehicles} vehicles"
        )


if __name__ == "__main__":
    main()
