"""Set-up shared by the processes that serve (`roadgrip serve`, and each of its ingest processes): memory management
tuned for the ingest path (garbage collection, free memory handed back), the estimator warmed up before traffic, the
resident memory as health reports it."""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import gc
import logging
import threading
import time
from pathlib import Path

from roadgrip.vehicle.params import PAPER_SUV

# The young generation's collection threshold (CPython's default: 700 allocations): the ingest path allocates about a
# dozen containers a sample (dicts, tuples, futures), so at 10,000 samples/s the default collects some 170 times a
# second.
SERVING_GC_THRESHOLD = 50_000
# How often a serving process hands the C allocator's free memory back to the system (glibc's malloc_trim). A sample's
# dict (17 keys) keeps its table in malloc's heap, not in Python's arenas; after a queue of 100,000 such dicts is freed
# the heap keeps the pages (+58 MB of RSS in `python results/trials/reliability/malloc_trim.py`) until malloc_trim(0) returns them
# (5 ms). So the service's RSS after a stall (a queue that filled, a long round) comes back down instead of staying at
# the stall's peak for good: the soak's memory steps of docs/RELIABILITY.md.
TRIM_INTERVAL_S = 10.0

log = logging.getLogger(__name__)


@functools.cache
def _malloc_trim():
    """glibc's malloc_trim, or None where the C library has none (musl, macOS)."""
    name = ctypes.util.find_library("c")
    libc = ctypes.CDLL(name) if name else None
    return getattr(libc, "malloc_trim", None)


def release_free_memory() -> bool:
    """Hand the C allocator's free pages back to the system; False where the C library cannot."""
    trim = _malloc_trim()
    if trim is None:
        return False
    trim(0)
    return True


def tune_memory_for_serving() -> None:
    """For a process that serves, once it has started:
    - move what exists now (modules, numba's kernels, the settings, the restored map) out of the collector's sight
      (`gc.freeze`) and collect the young generation every SERVING_GC_THRESHOLD allocations. Collection took 2.4 s
      instead of 7.4 s over the 40 s of `python results/trials/reliability/pipeline_cost.py --seconds 40`;
    - every TRIM_INTERVAL_S, hand free memory back (`release_free_memory`), from a daemon thread.
    Process-wide, hence not done by `CloudService.start`, which tests call many times in one process."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(SERVING_GC_THRESHOLD, *gc.get_threshold()[1:])
    if _malloc_trim() is None:
        log.info("the C library has no malloc_trim: free memory stays with the allocator")
        return

    def trim_periodically() -> None:
        while True:
            time.sleep(TRIM_INTERVAL_S)
            release_free_memory()

    threading.Thread(target=trim_periodically, name="roadgrip-malloc-trim", daemon=True).start()


def rss_mb(pid: int | str = "self") -> float | None:
    """A process's resident memory (Linux /proc), MB; None where it cannot be read."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return None
    rss = [line for line in status.splitlines() if line.startswith("VmRSS:")]
    return int(rss[0].split()[1]) / 1024.0 if rss else None


def warm_up(estimator) -> None:
    """One update on a made-up sample, so that compiling (or loading from numba's cache) the estimator's kernels
    happens before the process says it is up, not in the pipeline's first round (~15 s cold)."""
    state = estimator.start(PAPER_SUV)
    sample = {
        "vehicle_id": "warm-up",
        "timestamp_ms": 0,
        "latitude_deg": None,
        "longitude_deg": None,
        "speed_mps": 20.0,
        "accel_lon_mps2": 0.0,
        "accel_lat_mps2": 0.0,
        "yaw_rate_radps": 0.0,
        "steering_wheel_angle_rad": 0.0,
        "abs_active": False,
        "acc_active": False,
        "lateral_speed_mps": None,
        **{f"wheel_speed_{w}_radps": 20.0 / PAPER_SUV.wheel_radius_m for w in ("fl", "fr", "rl", "rr")},
    }
    for k in range(12):  # a learned model's window fills before it estimates
        estimator.update(state, {**sample, "timestamp_ms": 100 * k})
    estimator.update_many(state, [{**sample, "timestamp_ms": 100 * k} for k in range(12, 14)])  # the pipeline's step
