"""Latency from a sample's own time (its timestamp_ms) to its stored estimate, as the service reports it in health.

Two views, both cheap enough for every estimate at 10,000 a second:
- recent: the exact 50th and 99th percentiles of the last `window` latencies (a deque);
- since start: percentiles from a cumulative histogram of `bin_ms` wide bins up to `max_ms` (one more bin holds the
  rest), so that a soak can report its whole run and not only the last seconds. A percentile is read as the upper edge
  of its bin: at most `bin_ms` above the exact value, never below it. A latency of `max_ms` or more is reported as
  `max_ms` with `over_max` counting them.

A negative latency (a terminal's clock ahead of the server's) counts as 0 in the histogram and as it is in the recent
window.
"""

from __future__ import annotations

from collections import deque

import numpy as np


class LatencyRecorder:
    def __init__(self, window: int = 100_000, bin_ms: float = 10.0, max_ms: float = 600_000.0):
        if window < 1 or bin_ms <= 0 or max_ms <= bin_ms:
            raise ValueError(
                f"need window >= 1 and 0 < bin_ms < max_ms, got window={window!r}, bin_ms={bin_ms!r}, max_ms={max_ms!r}"
            )
        self.bin_ms = float(bin_ms)
        self.max_ms = float(max_ms)
        self._bins = int(np.ceil(max_ms / bin_ms))
        self._recent: deque[float] = deque(maxlen=window)
        self._histogram = np.zeros(self._bins + 1, dtype=np.int64)  # the last bin: max_ms and above

    def add(self, latencies_ms: np.ndarray) -> None:
        latencies_ms = np.asarray(latencies_ms, dtype=float)
        if latencies_ms.size == 0:
            return
        self._recent.extend(latencies_ms.tolist())
        index = np.clip(latencies_ms // self.bin_ms, 0, self._bins).astype(np.int64)
        self._histogram += np.bincount(index, minlength=self._bins + 1)

    def recent(self) -> dict[str, float | None]:
        """Exact percentiles over the last `window` latencies, ms."""
        if not self._recent:
            return {"p50_ms": None, "p99_ms": None, "n": 0}
        p50, p99 = (float(v) for v in np.percentile(np.fromiter(self._recent, float, len(self._recent)), [50, 99]))
        return {"p50_ms": p50, "p99_ms": p99, "n": len(self._recent)}

    def since_start(self) -> dict[str, float | int | None]:
        """Percentiles over every latency added, from the histogram (upper bin edges), ms."""
        n = int(self._histogram.sum())
        if n == 0:
            return {"p50_ms": None, "p99_ms": None, "n": 0, "over_max": 0}
        cumulative = np.cumsum(self._histogram)
        p50, p99 = (min(self.max_ms, (int(np.searchsorted(cumulative, q * n)) + 1) * self.bin_ms) for q in (0.5, 0.99))
        return {"p50_ms": p50, "p99_ms": p99, "n": n, "over_max": int(self._histogram[-1])}
