"""What the C allocator keeps after a burst of samples is freed, and what malloc_trim(0) gives back
(roadgrip/cloud/process.py, TRIM_INTERVAL_S): the RSS with 20,000 samples held (a steady queue), with a burst of
100,000 more (a queue after a stall), after the burst is freed, and after `release_free_memory()`; three times.

Run: python results/trials/reliability/malloc_trim.py   (docs/RELIABILITY.md)
"""

import time

import orjson

from roadgrip.bench.ingest import _message, sample_bodies
from roadgrip.cloud.process import release_free_memory, rss_mb


def main():
    run = sample_bodies(2)[0]

    def samples(n: int) -> list[dict]:
        return [orjson.loads(_message("car", 100 * i, run[i % len(run)])) for i in range(n)]

    held = samples(20_000)
    print(f"20,000 samples held: RSS {rss_mb():.0f} MB")
    for _ in range(3):
        burst = samples(100_000)
        peak = rss_mb()
        del burst
        freed = rss_mb()
        started = time.perf_counter()
        release_free_memory()
        took_ms = 1e3 * (time.perf_counter() - started)
        print(
            f"100,000 more: {peak:.0f} MB; freed: {freed:.0f} MB; after malloc_trim: {rss_mb():.0f} MB "
            f"({took_ms:.1f} ms)"
        )
    assert len(held) == 20_000


if __name__ == "__main__":
    main()
