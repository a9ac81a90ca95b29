"""Memory handed back by a serving process (roadgrip/cloud/process.py)."""

from __future__ import annotations

import orjson

from roadgrip.cloud.process import release_free_memory, rss_mb


def test_free_memory_goes_back_to_the_system_after_a_burst_of_samples():
    sample = orjson.dumps({f"field_{k}": float(k) for k in range(17)})  # a sample's dict: its table in malloc's heap
    burst = [orjson.loads(sample) for _ in range(200_000)]
    del burst
    before = rss_mb()
    assert release_free_memory()  # glibc, as on the machines we serve from
    assert rss_mb() < before - 40  # MB: the burst's tables (1 kB each) are freed pages now given back
