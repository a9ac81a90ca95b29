"""Admission of what vehicles send, in the process that owns them: the per-vehicle rate limit (HTTP and MQTT draw on
the same bucket), then the pipeline; for MQTT also parsing, rejections reported on the vehicle's error topic, the
acknowledgement once stored, and backpressure.

`Ingest` does it in the service's own process (`ingest_processes: 0`); `roadgrip.cloud.serve.shards.IngestShards` has the
same methods and hands each vehicle to the ingest process that owns it, where an `Ingest` does the same.
"""

from __future__ import annotations

import collections
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Generic, TypeVar

from roadgrip.cloud.ingest.ratelimit import RateLimiter
from roadgrip.cloud.ingest.wire import PayloadError, parse_payload
from roadgrip.cloud.metrics import MAIN_PROCESS, TRANSPORTS, IngestCounters, ProcessView
from roadgrip.cloud.pipeline.pipeline import Pipeline, SubmitResult
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mqtt import Busy

# Samples the MQTT side may queue for a pipeline (2 s of 1,000 vehicles at 10 Hz). Beyond it the MQTT handler raises
# Busy: the message stays unacknowledged in the broker's persistent session and comes again once the backlog is down to
# half (`has_room`; MqttClient reconnects for it), while paho's network thread goes on reading and pinging. The
# Receive Maximum (SERVICE_RECEIVE_MAXIMUM messages) would bound it by itself on a broker that keeps to it; Mosquitto
# 2.0.11 does not (tests/cloud/serve/test_edge_intake.py). It also bounds a round: with 100,000 a service that fell
# behind ran rounds of 10 s and more, and each added its queue to the RSS for good (the allocator keeps its peak).
MAX_MQTT_BACKLOG = 20_000

Rejecter = Callable[[str, list[dict]], None]  # (vehicle_id, rejections as dicts with index, field, reason)
Delivery = TypeVar("Delivery")


class IngestUnavailable(RuntimeError):
    """The process that owns the vehicle (an ingest process, or the broker in cluster mode) could not take the
    request: nothing is acknowledged (503)."""


class RateLimited(Exception):
    """The vehicle is over its rate limit; nothing was stored. `retry_after_s` is infinite when the message alone
    exceeds the burst (it would never pass)."""

    def __init__(self, reason: str, retry_after_s: float):
        super().__init__(reason, retry_after_s)
        self.reason = reason
        self.retry_after_s = retry_after_s

    def __str__(self) -> str:
        return self.reason


class Ingest:
    def __init__(self, settings: Settings, pipeline: Pipeline, reject: Rejecter):
        self.settings = settings
        self.pipeline = pipeline
        self.rate_limiter = RateLimiter(settings.rate_limit_samples_per_s, settings.rate_limit_burst_s)
        self.reject = reject
        self.counters = IngestCounters()

    def start(self) -> None:
        self.pipeline.start()

    def stop(self) -> None:
        self.pipeline.stop()

    @property
    def backlog(self) -> int:
        """Samples submitted and not yet taken by a round."""
        return self.pipeline.backlog

    def submit(
        self, vehicle_id: str, samples: list[dict], received: int, *, retry: bool = False, transport: str = "http"
    ) -> Future:
        """Valid samples of one vehicle, out of `received` (rejected ones included: all count against the rate
        limit), arrived over `transport` (http or mqtt: counted for the metrics). The future resolves to a
        SubmitResult once they are stored (at once when there are none), or fails with RateLimited, or with
        StorageUnavailable while storage is down unless `retry` (Pipeline.submit)."""
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {TRANSPORTS}, got {transport!r}")
        decision = self.rate_limiter.allow(vehicle_id, received, time.monotonic())
        counters = vars(self.counters)
        counters[f"received_{transport}"] += received
        if not decision.allowed:
            counters[f"rate_limited_{transport}"] += received
            future: Future = Future()
            future.set_exception(RateLimited(decision.reason, decision.retry_after_s))
            return future
        counters[f"invalid_{transport}"] += received - len(samples)
        if samples:
            return self.pipeline.submit(vehicle_id, samples, retry=retry)
        future = Future()
        future.set_result(SubmitResult(0, 0))
        return future

    def mqtt_message(self, vehicle_id: str, payload: bytes, ack: Callable[[], None]) -> None:
        """One MQTT message from a vehicle (the broker's ACL made sure it is that vehicle): parse, report rejections
        on the vehicle's error topic, queue the valid samples, acknowledge once they are stored. A message refused as
        a whole (unreadable, over the rate limit) is acknowledged at once: the broker must not deliver it again.
        Raises Busy, before reading it, while MAX_MQTT_BACKLOG samples wait (backpressure: the broker keeps it)."""
        if self.pipeline.backlog > MAX_MQTT_BACKLOG and self.pipeline.running:
            raise Busy(f"{self.pipeline.backlog} samples wait for the pipeline")
        s = self.settings
        try:
            samples, errors = parse_payload(
                payload,
                now_ms=int(time.time() * 1000),
                vehicle_id=vehicle_id,
                max_bytes=s.max_payload_bytes,
                max_samples=s.max_samples_per_payload,
                max_future_ms=int(s.max_future_s * 1000),
            )
        except PayloadError as exc:
            self.counters.unreadable_mqtt += 1
            self.reject(vehicle_id, [{"index": None, "field": exc.field, "reason": str(exc)}])
            ack()
            return
        future = self.submit(vehicle_id, samples, len(samples) + len(errors), retry=True, transport="mqtt")
        if isinstance(future.exception() if future.done() else None, RateLimited):
            self.reject(vehicle_id, [{"index": None, "field": None, "reason": str(future.exception())}])
            ack()
            return
        if errors:
            self.reject(vehicle_id, [e.to_dict() for e in errors])
        future.add_done_callback(lambda f: ack() if f.exception() is None else None)

    def has_room(self) -> bool:
        """Whether messages refused with Busy may come again: the pipeline's backlog down to half its bound."""
        return self.pipeline.backlog <= MAX_MQTT_BACKLOG // 2

    def forget_vehicle(self, vehicle_id: str, drop_queued: bool = False) -> None:
        self.pipeline.forget_vehicle(vehicle_id, drop_queued)

    def stats(self) -> dict:
        """The pipeline's counters, its backlog and whether its writes fail (health: `pipeline`)."""
        return {
            **self.pipeline.counters.to_dict(),
            "backlog": self.pipeline.backlog,
            "storage_down": self.pipeline.storage_down,
        }

    def metrics(self) -> dict:
        """What the metrics need beside `stats` (roadgrip/cloud/metrics.py): the admission counters and the
        estimator's time per update."""
        return {"ingest": self.counters.to_dict(), "estimator_seconds": self.pipeline.estimator_time.state()}

    def views(self) -> list[ProcessView]:
        """This process's pipeline, for the metrics."""
        return [ProcessView(MAIN_PROCESS, self.stats(), self.metrics())]


class WaitingLine(Generic[Delivery]):
    """The MQTT deliveries a pipeline had no room for (`Busy`), in the order they came, each unacknowledged until it
    is handed over: the one rule of backpressure for the processes that read a broker (an ingest process,
    roadgrip/cloud/serve/shards.py; a cluster worker's partition, roadgrip/cloud/cluster/worker.py). `hand` gives one
    delivery to the pipeline and says whether it took it (False on Busy); `has_room` says whether refused deliveries
    may come again (`Ingest.has_room`)."""

    def __init__(self, has_room: Callable[[], bool], hand: Callable[[Delivery], bool]):
        self.has_room = has_room
        self.hand = hand
        self.line: collections.deque[Delivery] = collections.deque()

    def __len__(self) -> int:
        return len(self.line)

    def offer(self, delivery: Delivery) -> None:
        """A new delivery: handed over at once unless earlier ones wait (the broker's order is kept) or the pipeline
        has no room; else it waits."""
        if self.line or not self.hand(delivery):
            self.line.append(delivery)

    def drain(self) -> None:
        """Hand what waits over, in order, once the pipeline has room again (`Ingest.has_room`: its backlog down to
        half its bound), until it refuses one."""
        if not self.line or not self.has_room():
            return
        while self.line and self.hand(self.line[0]):
            self.line.popleft()
