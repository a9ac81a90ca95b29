"""The per-vehicle rate limit on ingest: a token bucket per vehicle, in samples.

A vehicle's bucket holds at most `samples_per_s * burst_s` samples (the burst) and fills at `samples_per_s`; a message
of n samples (HTTP request or MQTT message, valid or not: parsing them is the work) takes n from it, or is refused
whole when fewer are left, taking nothing. Over any interval of T seconds a vehicle therefore gets at most
burst + samples_per_s * T samples through. The defaults (50 samples/s, 10 s of burst: 500 samples) are five times the
10 Hz of a terminal, and leave room for a terminal that buffered a tunnel's worth of samples to catch up.

A message larger than the whole burst could never pass: it is refused with `retry_after_s` infinite, and the reason
says to split it.

`allow` is O(1) and thread-safe (HTTP requests on the event loop, MQTT messages on paho's thread share one limiter).
Memory stays bounded by the vehicles that sent within the last `burst_s`: a vehicle silent that long has a full bucket
again, the same as one never seen, so it is forgotten (amortised O(1): buckets are kept in order of last use and the
oldest are dropped as they come due). Vehicles are authenticated before they reach the limiter, so their number is
bounded by the registered ones in any case.

`samples_per_s` 0 turns the limit off.

    limiter = RateLimiter(samples_per_s=50.0, burst_s=10.0)
    decision = limiter.allow("car-1", len(samples), time.monotonic())
    if not decision.allowed:
        ...  # HTTP 429 with Retry-After: decision.retry_after_s; MQTT: decision.reason on the error topic
"""

from __future__ import annotations

import math
import threading
from collections import OrderedDict
from dataclasses import dataclass


@dataclass(frozen=True)
class Decision:
    """What `RateLimiter.allow` decided: `retry_after_s` is 0 when allowed, the wait until the same message would
    pass when refused (infinite when it never would: larger than the burst), `reason` says why in words."""

    allowed: bool
    retry_after_s: float = 0.0
    reason: str = ""


ALLOWED = Decision(True)


@dataclass
class _Bucket:
    tokens: float  # samples the vehicle may still send now
    updated_s: float  # when `tokens` was last brought up to date


class RateLimiter:
    """Token buckets by vehicle id (module docstring). `now_s` is any monotonic clock in seconds, given by the caller
    (`time.monotonic()` in the service, a fake one in tests)."""

    def __init__(self, samples_per_s: float = 50.0, burst_s: float = 10.0):
        if not (
            isinstance(samples_per_s, (int, float))
            and not isinstance(samples_per_s, bool)
            and math.isfinite(samples_per_s)
            and samples_per_s >= 0
        ):
            raise ValueError(f"samples_per_s must be a finite number >= 0 (0: no limit), got {samples_per_s!r}")
        if not (
            isinstance(burst_s, (int, float))
            and not isinstance(burst_s, bool)
            and math.isfinite(burst_s)
            and burst_s > 0
        ):
            raise ValueError(f"burst_s must be a finite number > 0, got {burst_s!r}")
        self.samples_per_s = float(samples_per_s)
        self.burst_s = float(burst_s)
        self._buckets: OrderedDict[str, _Bucket] = OrderedDict()  # by last use, oldest first
        self._lock = threading.Lock()

    @property
    def enabled(self) -> bool:
        return self.samples_per_s > 0

    @property
    def burst(self) -> float:
        """The bucket's size: samples a vehicle may send at once after a quiet spell."""
        return self.samples_per_s * self.burst_s

    @property
    def tracked(self) -> int:
        """Vehicles whose bucket is remembered (those that sent within the last burst_s, at the last call)."""
        with self._lock:
            return len(self._buckets)

    def allow(self, vehicle_id: str, n: int, now_s: float) -> Decision:
        """Take `n` samples from `vehicle_id`'s bucket at time `now_s` if it holds them (allowed), else take nothing
        and say how long to wait."""
        if isinstance(n, bool) or not isinstance(n, int) or n < 0:
            raise ValueError(f"n must be a whole number of samples >= 0, got {n!r}")
        if not self.enabled:
            return ALLOWED
        burst = self.burst
        with self._lock:
            self._forget_idle(now_s)
            bucket = self._buckets.pop(vehicle_id, None)
            if bucket is None:
                bucket = _Bucket(burst, now_s)
            elif now_s > bucket.updated_s:  # a clock that went back refills nothing
                # tokens += elapsed * rate, up to the burst
                bucket.tokens = min(burst, bucket.tokens + (now_s - bucket.updated_s) * self.samples_per_s)
                bucket.updated_s = now_s
            self._buckets[vehicle_id] = bucket  # now the most recently used
            if n <= bucket.tokens:
                bucket.tokens -= n
                return ALLOWED
            tokens = bucket.tokens
        if n > burst:
            return Decision(
                False,
                math.inf,
                f"{n} samples in one message exceed vehicle {vehicle_id}'s burst of "
                f"{burst:g} samples (rate limit {self.samples_per_s:g} samples/s, "
                f"{self.burst_s:g} s of burst): send at most {math.floor(burst)} a "
                "message",
            )
        wait_s = (n - tokens) / self.samples_per_s
        return Decision(
            False,
            wait_s,
            f"vehicle {vehicle_id} is over its rate limit of {self.samples_per_s:g} "
            f"samples/s ({self.burst_s:g} s of burst): {n} samples refused, none stored; "
            f"retry in {wait_s:.1f} s",
        )

    def _forget_idle(self, now_s: float) -> None:
        """Drop the buckets unused for burst_s or longer: they are full again, as a new one would be."""
        while self._buckets:
            oldest = next(iter(self._buckets.values()))
            if now_s - oldest.updated_s < self.burst_s:
                return
            self._buckets.popitem(last=False)
