"""Prometheus metrics (`GET /metrics`, text exposition format) with the maintained client library, prometheus_client.

Nothing here runs on the hot path. The service already counts what it does in plain integers (the pipeline's
`PipelineCounters`, `IngestCounters` below, the fan-out's warning changes, the service's dropped estimate messages):
they are read when Prometheus scrapes, by `ServiceCollector`, a custom collector on a registry of the app's own (not
the library's global one: one process may hold several services, as the tests do). The two histograms are filled per
round, not per sample (`BatchHistogram`: one numpy bincount a round).

Ingest processes (`ingest_processes` > 1, roadgrip/cloud/serve/shards.py): their counters live in other processes. Each
already sends its pipeline's counters to the service's process every STATS_INTERVAL_S; it sends its metrics
(`Ingest.metrics`) in the same message, and the collector exposes every process's figures with the label
`process` ("main": the service's own process, "ingest-0", "ingest-1", ...). That is simpler than prometheus_client's
multiprocess mode (PROMETHEUS_MULTIPROC_DIR), which needs an environment variable set before the library is imported
in every process, a directory wiped at each start and the files of dead processes marked, gives mmap-backed values a
lock per increment, and does not support custom collectors; and it is as exact: a scrape sees each ingest process's
figures as of its last message (at most 0.5 s old). A restarted ingest process starts its counters from zero, which
Prometheus treats as a counter reset (rate() and increase() handle it).

A later process of another role (a worker, an API replica) reuses this module: a collector that yields its own
families with `counter`, `gauge` and `histogram`, on a registry made by `registry_with`.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np
from prometheus_client import CollectorRegistry, PlatformCollector, ProcessCollector
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

# sample time to stored estimate: a round every flush_interval_s (0.1 s) after the reorder window (0.3 s), plus the
# terminal's own batching (1 s for 10 samples a message); the soaks' p50 was ~1 s and p99 1.7-6 s (docs/RELIABILITY.md);
# a stalled service runs into minutes
LATENCY_BUCKETS_S = (0.1, 0.25, 0.5, 1.0, 1.5, 2.0, 3.0, 5.0, 10.0, 30.0, 60.0, 300.0)
# one estimator update: pmf median 13 us, p99 52 us; the EKF ~8 us; the learned model ~0.7 ms (docs/PRODUCTION.md
# "Speed", docs/ESTIMATORS.md); a pause of the process more
ESTIMATOR_BUCKETS_S = (5e-6, 1e-5, 2.5e-5, 5e-5, 1e-4, 2.5e-4, 5e-4, 1e-3, 2.5e-3, 1e-2, 0.1)
TRANSPORTS = ("http", "mqtt")
MAIN_PROCESS = "main"


class BatchHistogram:
    """A histogram filled with whole batches of observations (`add`: one numpy call a batch), read by a scrape
    (`state`, then `histogram`). Negative observations (a terminal's clock ahead of the server's) count as 0. Safe
    across threads (one lock a batch)."""

    def __init__(self, buckets: Iterable[float]):
        self.buckets = tuple(float(b) for b in buckets)
        if not self.buckets or any(b <= a for a, b in zip(self.buckets, self.buckets[1:])) or self.buckets[0] <= 0:
            raise ValueError(f"buckets must be positive and increasing, got {buckets!r}")
        self._edges = np.asarray(self.buckets)
        self._counts = np.zeros(len(self.buckets) + 1, dtype=np.int64)  # the last: above the largest bucket
        self._sum = 0.0
        self._lock = threading.Lock()

    def add(self, values) -> None:
        values = np.maximum(np.asarray(values, dtype=float), 0.0)
        if values.size == 0:
            return
        # a value equal to a bucket's upper bound belongs to it (Prometheus buckets are "less or equal")
        counts = np.bincount(np.searchsorted(self._edges, values, side="left"), minlength=len(self._counts))
        with self._lock:
            self._counts += counts
            self._sum += float(values.sum())

    def state(self) -> dict:
        """Counts per bucket (not cumulative, the last above every bucket) and the sum: what an ingest process sends."""
        with self._lock:
            return {"counts": self._counts.tolist(), "sum": self._sum}


@dataclass
class IngestCounters:
    """What an `Ingest` (roadgrip/cloud/ingest/admission.py) admitted and refused, per transport, before the pipeline: plain
    integers, each written by one thread only (HTTP: the event loop or an ingest process's channel; MQTT: paho's
    network thread or the same channel)."""

    received_http: int = 0  # samples in readable payloads, valid or not, rate limited or not
    received_mqtt: int = 0
    invalid_http: int = 0  # samples refused by validation (roadgrip/cloud/ingest/wire.py)
    invalid_mqtt: int = 0
    rate_limited_http: int = 0  # samples refused by the vehicle's rate limit (every sample of the payload)
    rate_limited_mqtt: int = 0
    unreadable_mqtt: int = 0  # MQTT messages refused whole (not UTF-8 or JSON, empty, too large, too many samples)

    def to_dict(self) -> dict:
        return dict(vars(self))


@dataclass(frozen=True)
class ProcessView:
    """One process's pipeline as the collector reads it: its label, `Ingest.stats()`, `Ingest.metrics()`; for an
    ingest process also its restarts, whether it is alive, its resident memory and the MQTT messages forwarded to it
    and not yet acknowledged."""

    process: str
    stats: dict
    metrics: dict
    restarts: int | None = None
    alive: bool | None = None
    rss_bytes: float | None = None
    forwarded_unacknowledged: int | None = None


def counter(
    name: str, documentation: str, series: Iterable[tuple[list[str], float]], labels: Iterable[str] = ()
) -> CounterMetricFamily:
    """A counter family (`name` without `_total`: the library adds it) with one series per (label values, value)."""
    result = CounterMetricFamily(name, documentation, labels=list(labels))
    for label_values, value in series:
        result.add_metric(label_values, value)
    return result


def gauge(
    name: str, documentation: str, series: Iterable[tuple[list[str], float]], labels: Iterable[str] = ()
) -> GaugeMetricFamily:
    result = GaugeMetricFamily(name, documentation, labels=list(labels))
    for label_values, value in series:
        result.add_metric(label_values, value)
    return result


def histogram(
    name: str,
    documentation: str,
    buckets: tuple[float, ...],
    series: Iterable[tuple[list[str], dict]],
    labels: Iterable[str] = (),
) -> HistogramMetricFamily:
    """A histogram family with one series per (label values, `BatchHistogram.state()` of a histogram of `buckets`)."""
    result = HistogramMetricFamily(name, documentation, labels=list(labels))
    bounds = [*(f"{b:g}" for b in buckets), "+Inf"]
    for label_values, state in series:
        result.add_metric(label_values, list(zip(bounds, np.cumsum(state["counts"]).tolist())), state["sum"])
    return result


def registry_with(collector: Collector) -> CollectorRegistry:
    """A registry of its own with `collector` and the library's process_* and python_* metrics of this process."""
    registry = CollectorRegistry(auto_describe=False)
    registry.register(collector)
    ProcessCollector(registry=registry)
    PlatformCollector(registry=registry)
    return registry


def pipeline_metrics(views: list[ProcessView], http_payloads_rejected: int | None = None) -> Iterator[Metric]:
    """The families of every process that runs pipelines (`roadgrip serve`, `roadgrip worker`): admission, storage,
    estimation and checkpoints, per process (`Ingest.views()`). `http_payloads_rejected`: the HTTP requests refused
    whole by a service (None where there is no HTTP ingest)."""

    def per(key: str) -> list[tuple[list[str], float]]:
        return [([v.process], v.stats[key]) for v in views]

    ingest = [(v.process, v.metrics["ingest"]) for v in views]
    yield counter(
        "roadgrip_samples_received",
        "Samples received in readable payloads (valid or not), by the process that admitted them and transport",
        [([p, t], c[f"received_{t}"]) for p, c in ingest for t in TRANSPORTS],
        ["process", "transport"],
    )
    yield counter(
        "roadgrip_samples_rejected",
        "Samples refused: invalid (validation) or rate_limited",
        [
            ([p, t, reason], c[f"{reason}_{t}"])
            for p, c in ingest
            for t in TRANSPORTS
            for reason in ("invalid", "rate_limited")
        ],
        ["process", "transport", "reason"],
    )
    yield counter(
        "roadgrip_payloads_rejected",
        "HTTP requests and MQTT messages refused whole before any sample "
        "was read (not UTF-8 or JSON, empty, too large, too many samples, wrong content type)",
        ([] if http_payloads_rejected is None else [([MAIN_PROCESS, "http"], http_payloads_rejected)])
        + [([p, "mqtt"], c["unreadable_mqtt"]) for p, c in ingest],
        ["process", "transport"],
    )
    yield counter("roadgrip_samples_stored", "Samples newly stored", per("stored"), ["process"])
    yield counter(
        "roadgrip_samples_duplicate",
        "Samples already stored (a repeated request or MQTT redelivery)",
        per("duplicates"),
        ["process"],
    )
    yield counter(
        "roadgrip_samples_late",
        "Samples stored but not estimated: older than one already estimated",
        per("late"),
        ["process"],
    )
    yield counter("roadgrip_estimates", "Estimates made and stored", per("estimates"), ["process"])
    yield counter(
        "roadgrip_estimator_restarts",
        "Estimators restarted after a gap longer than max_gap_s",
        per("restarts"),
        ["process"],
    )
    yield counter("roadgrip_pipeline_rounds", "Pipeline rounds run", per("rounds"), ["process"])
    yield counter(
        "roadgrip_pipeline_failed_rounds",
        "Pipeline rounds whose write failed (storage down: retried)",
        per("failed_rounds"),
        ["process"],
    )
    yield counter(
        "roadgrip_pipeline_slow_rounds", "Pipeline rounds that took over 1 s", per("slow_rounds"), ["process"]
    )
    yield counter(
        "roadgrip_pipeline_estimate_seconds",
        "Seconds spent in reorder buffers and estimators",
        per("estimate_s"),
        ["process"],
    )
    yield counter(
        "roadgrip_pipeline_write_seconds",
        "Seconds spent writing rounds (telemetry and estimates)",
        per("write_s"),
        ["process"],
    )
    yield counter("roadgrip_checkpoints_written", "Estimator states stored", per("checkpoints_written"), ["process"])
    yield counter(
        "roadgrip_checkpoints_restored",
        "Vehicles that went on from a stored estimator state",
        per("checkpoints_restored"),
        ["process"],
    )
    yield gauge(
        "roadgrip_pipeline_backlog_samples",
        "Samples submitted and not yet taken by a round",
        per("backlog"),
        ["process"],
    )
    yield gauge(
        "roadgrip_pipeline_last_round_seconds", "Duration of the last pipeline round", per("last_round_s"), ["process"]
    )
    yield gauge(
        "roadgrip_pipeline_storage_failing",
        "1 while the pipeline's writes fail and it holds a round",
        [([v.process], float(v.stats["storage_down"])) for v in views],
        ["process"],
    )
    yield histogram(
        "roadgrip_estimator_update_seconds",
        "Time of one estimator update",
        ESTIMATOR_BUCKETS_S,
        [([v.process], v.metrics["estimator_seconds"]) for v in views],
        ["process"],
    )


def estimate_latency(latency: BatchHistogram) -> HistogramMetricFamily:
    """The latency family from a BatchHistogram of LATENCY_BUCKETS_S, in seconds."""
    return histogram(
        "roadgrip_estimate_latency_seconds",
        "From a sample's own time (timestamp_ms) to its stored estimate",
        LATENCY_BUCKETS_S,
        [([], latency.state())],
    )


class ServiceCollector(Collector):
    """The metrics of `roadgrip serve` (docs/CLOUD.md "Metrics (Prometheus)"), read from a started CloudService
    (roadgrip/cloud/serve/service.py) at each scrape: each process's pipeline from `service.ingest.views()`, the rest from
    the service's own process."""

    def __init__(self, service):
        self.service = service

    def collect(self) -> Iterator[Metric]:
        service = self.service
        views = service.ingest.views()
        yield from pipeline_metrics(views, http_payloads_rejected=service.http_payloads_rejected)
        shards = [v for v in views if v.restarts is not None]
        if shards:
            yield counter(
                "roadgrip_ingest_process_restarts",
                "Ingest processes started again after they stopped",
                [([v.process], v.restarts) for v in shards],
                ["process"],
            )
            yield gauge(
                "roadgrip_ingest_process_up",
                "1 while the ingest process is alive",
                [([v.process], float(v.alive)) for v in shards],
                ["process"],
            )
            yield gauge(
                "roadgrip_ingest_process_resident_memory_bytes",
                "Resident memory of the ingest process",
                [([v.process], v.rss_bytes) for v in shards if v.rss_bytes is not None],
                ["process"],
            )
            yield gauge(
                "roadgrip_mqtt_forwarded_unacknowledged_messages",
                "MQTT messages forwarded to the ingest process and not yet acknowledged by it (stored)",
                [([v.process], v.forwarded_unacknowledged) for v in shards],
                ["process"],
            )
        fanout = service.fanout
        yield estimate_latency(fanout.latency_histogram)
        yield counter(
            "roadgrip_warnings",
            "Warning changes: raised, refreshed, cancelled, expired",
            [([change], n) for change, n in fanout.warning_changes.items()],
            ["change"],
        )
        mqtt = service.mqtt
        yield gauge(
            "roadgrip_mqtt_connected",
            "1 while the service's MQTT connection is up (0 also with MQTT off)",
            [([], float(mqtt is not None and mqtt.connected))],
        )
        yield gauge(
            "roadgrip_mqtt_publishes_waiting",
            "The service's own MQTT publishes not yet acknowledged",
            [([], 0 if mqtt is None else mqtt.unacknowledged)],
        )
        yield counter(
            "roadgrip_mqtt_estimate_messages_dropped",
            "Estimate messages not published because the broker was behind (the estimates are stored)",
            [([], service.estimate_messages_dropped)],
        )
