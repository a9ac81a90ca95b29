"""Bytes the SQLite store writes to disk per 1,000 telemetry rows (one 100 ms sample of 1,000 vehicles) with their
estimates, by how many such rounds go into one transaction (the pipeline writes one a round, every
`flush_interval_s`, 0.1 s by default).

A transaction touches about one leaf page of the (vehicle_id, timestamp_ms) key index per vehicle in each table,
whatever the number of rows, and the WAL holds every touched page whole; so the bytes per row fall with the rows per
transaction. Reads /proc/self/io (write_bytes: what reached the block layer, WAL and database together).

Run: python results/trials/reliability/sqlite_write_volume.py [--rounds 1500]   (docs/RELIABILITY.md)
"""

import argparse
import json
import tempfile
import time
from pathlib import Path

from roadgrip.bench.ingest import _message, sample_bodies
from roadgrip.cloud.storage.database import open_storage

VEHICLES = 1000
SAMPLE_MS = 100
ESTIMATE = {
    "mu": 0.5,
    "mu_lower": 0.1,
    "mu_upper": 0.9,
    "excited": False,
    "estimator": "ekf",
    "latitude_deg": 38.0,
    "longitude_deg": 114.5,
    "h3_cell": "8a319c910307fff",
}


def written_bytes() -> int:
    for line in Path("/proc/self/io").read_text().splitlines():
        if line.startswith("write_bytes:"):
            return int(line.split()[1])
    raise RuntimeError("no write_bytes in /proc/self/io")


def measure(rounds: int, rounds_per_commit: int, bodies) -> tuple[float, float]:
    """(MB written per 1,000-row round, telemetry rows per second)."""
    samples = [json.loads(_message(f"v{i:05d}", 0, bodies[i % len(bodies)][i % 300])) for i in range(VEHICLES)]
    base_ms = 1_790_000_000_000
    with tempfile.TemporaryDirectory(prefix="roadgrip-wal-") as tmp:
        storage = open_storage(f"sqlite:///{tmp}/volume.sqlite")
        before, started = written_bytes(), time.perf_counter()
        for first in range(0, rounds, rounds_per_commit):
            rows = [
                {**s, "timestamp_ms": base_ms + (first + k) * SAMPLE_MS}
                for k in range(rounds_per_commit)
                for s in samples
            ]
            storage.write_batch(
                rows, [{"vehicle_id": r["vehicle_id"], "timestamp_ms": r["timestamp_ms"], **ESTIMATE} for r in rows]
            )
        elapsed, written = time.perf_counter() - started, written_bytes() - before
        storage.close()
    return written / rounds / 1e6, rounds * VEHICLES / elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=1500, help="100 ms rounds of 1,000 vehicles to write")
    args = parser.parse_args()
    bodies = sample_bodies(2)
    print("rounds a transaction | MB written a round | MB/s at 10,000 samples/s | rows/s")
    for per_commit in (1, 5, 10):
        mb, rate = measure(args.rounds, per_commit, bodies)
        print(f"{per_commit:20d} | {mb:18.2f} | {10 * mb:24.0f} | {rate:,.0f}", flush=True)


if __name__ == "__main__":
    main()
