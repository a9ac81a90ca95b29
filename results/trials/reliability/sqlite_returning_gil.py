"""What RETURNING costs SQLite inserts when another thread is busy in Python, as paho's network thread is in the
service: rows per second through 500-row INSERT ... ON CONFLICT DO NOTHING statements (1,000 rows a transaction, the
telemetry of 1,000 vehicles), counting the rows with RETURNING or with the cursor's rowcount, with the other thread
idle and busy.

Run: python results/trials/reliability/sqlite_returning_gil.py [--rows 50000]   (quoted in Storage.write_batch and docs/RELIABILITY.md)
"""

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path

from roadgrip.bench.ingest import _message, sample_bodies
from roadgrip.cloud.storage.database import open_storage, telemetry_table

STATEMENT_ROWS = 500


def rows_per_s(samples: list[dict], returning: bool, busy: bool) -> float:
    stop = threading.Event()

    def spin():
        x = 0
        while not stop.is_set():
            for i in range(1000):
                x += i

    other = threading.Thread(target=spin)
    if busy:
        other.start()
    columns = [c.name for c in telemetry_table.columns]
    with tempfile.TemporaryDirectory(prefix="roadgrip-gil-") as tmp:
        storage = open_storage(f"sqlite:///{Path(tmp) / 'gil.sqlite'}")
        sql = storage._insert_sql(telemetry_table, STATEMENT_ROWS, returning)
        started = time.perf_counter()
        for k in range(0, len(samples), 2 * STATEMENT_ROWS):
            with storage._engine.begin() as conn:
                for first in (k, k + STATEMENT_ROWS):
                    values = tuple(row[c] for row in samples[first : first + STATEMENT_ROWS] for c in columns)
                    result = conn.exec_driver_sql(sql, values)
                    if returning:
                        result.all()
        elapsed = time.perf_counter() - started
        storage.close()
    stop.set()
    if busy:
        other.join()
    return len(samples) / elapsed


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rows", type=int, default=50_000, help="a multiple of 1,000")
    args = parser.parse_args()
    bodies = sample_bodies(2)
    samples = [
        json.loads(
            _message(
                f"gil-{k % 1000:04d}",
                1_700_000_000_000 + (k // 1000) * 100,
                bodies[k % 2][(k // 1000) % len(bodies[k % 2])],
            )
        )
        for k in range(args.rows)
    ]
    for busy in (False, True):
        for returning in (True, False):
            print(
                f"other thread {'busy' if busy else 'idle'}, {'RETURNING' if returning else 'rowcount '}: "
                f"{rows_per_s(samples, returning, busy):9,.0f} rows/s",
                flush=True,
            )


if __name__ == "__main__":
    main()
