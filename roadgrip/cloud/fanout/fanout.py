"""What follows once a round's estimates are stored (step 6 of roadgrip/cloud/worker/pipeline.py): the friction map and the
warning engine take them, warning changes are stored, warning DENMs are published at once, and each vehicle's estimates
go out together on its friction topic, one message (a JSON array) per `friction_publish_interval_s`. The latency from
a sample's own time to its stored estimate is recorded here too (health: `latency`, `latency_since_start`).

There is one Fanout in a service, in its main process, since the map and the warnings need every vehicle: the
pipeline calls it in the same process, and with `ingest_processes` the pipelines of the ingest processes send it
what they stored (roadgrip/cloud/worker/shards.py). Calls from several threads are serialised by one lock.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time

import numpy as np
import orjson

from roadgrip.cloud.edge.mqtt import WARNINGS_TOPIC, friction_topic
from roadgrip.cloud.fanout.friction_map import FrictionMap
from roadgrip.cloud.fanout.warning_engine import ACTIVE, EXPIRED, WarningEngine
from roadgrip.cloud.latency import LatencyRecorder
from roadgrip.cloud.metrics import LATENCY_BUCKETS_S, BatchHistogram
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage

log = logging.getLogger(__name__)

WARNING_CHANGES = ("raised", "refreshed", "cancelled", "expired")
ESTIMATE_FIELDS = ("vehicle_id", "timestamp_ms", "mu", "mu_lower", "mu_upper", "excited", "estimator", "mu_proven",
                   "latitude_deg", "longitude_deg", "h3_cell")


def _estimate_message(row: dict) -> dict:
    return {k: row[k] for k in ESTIMATE_FIELDS}


def _change(event) -> str:
    """A warning event as one of WARNING_CHANGES (roadgrip/cloud/fanout/warning_engine.py: status, reason, sequence_number)."""
    if event.status == ACTIVE:
        return "refreshed" if event.sequence_number else "raised"
    return "expired" if event.reason == EXPIRED else "cancelled"


class Fanout:
    def __init__(self, storage: Storage, settings: Settings, friction_map: FrictionMap,
                 warning_engine: WarningEngine, publish=None):
        self.storage = storage
        self.settings = settings
        self.friction_map = friction_map
        self.warning_engine = warning_engine
        self.publish = publish  # callable(topic, payload bytes) or None
        self.latency = LatencyRecorder()  # sample time to stored estimate
        self.latency_histogram = BatchHistogram(LATENCY_BUCKETS_S)  # the same, in seconds, for the metrics
        self.warning_changes = dict.fromkeys(WARNING_CHANGES, 0)  # warning events by change (metrics)
        self.busy_s = 0.0  # seconds spent in `stored` since start (health: pipeline.fanout_s)
        self._newest_data_ms = 0
        # vehicle -> (when its oldest unpublished estimate was queued, monotonic s; the estimate messages)
        self._outbox: dict[str, tuple[float, list[dict]]] = {}
        self._lock = threading.Lock()

    def now_ms(self) -> int:
        """The service's clock for the map and warnings: the server's, or the newest stored sample's (`map_clock`)."""
        if self.settings.map_clock == "data":
            return self._newest_data_ms
        return int(time.time() * 1000)

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        """A round was stored at `stored_ms` (ms since epoch) with these estimates; its newest sample's timestamp."""
        with self._lock:
            started = time.perf_counter()
            self._newest_data_ms = max(self._newest_data_ms, newest_data_ms)
            if estimates:
                latencies_ms = stored_ms - np.fromiter((e["timestamp_ms"] for e in estimates), float, len(estimates))
                self.latency.add(latencies_ms)
                self.latency_histogram.add(latencies_ms / 1000.0)
                self._after_store(estimates)
            self.busy_s += time.perf_counter() - started

    def tick(self, final: bool = False) -> None:
        """Publish the estimates of each vehicle whose oldest unpublished one waited friction_publish_interval_s
        (all of them when `final`). Called after every round."""
        with self._lock:
            if not self._outbox:
                return
            due_since = time.monotonic() - self.settings.friction_publish_interval_s
            due = [v for v, (since, _) in self._outbox.items() if final or since <= due_since]
            for vehicle_id in due:
                self.publish(friction_topic(vehicle_id), orjson.dumps(self._outbox.pop(vehicle_id)[1]))

    def _after_store(self, estimates: list[dict]) -> None:
        now_ms = self.now_ms()
        self.friction_map.add(estimates, now_ms)
        self._warnings_out(self.warning_engine.update(estimates, now_ms), "")
        if self.publish is None:
            return
        now_s = time.monotonic()
        for row in estimates:
            self._outbox.setdefault(row["vehicle_id"], (now_s, []))[1].append(_estimate_message(row))

    def station_reports(self, rows: list[dict]) -> None:
        """The evidence of newly stored roadside station reports (roadgrip/cloud/fanout/stations.py, evidence_rows: one row
        per covered cell) into the map and the warning engine, under the lock; warning changes stored and their DENMs
        published as after a round of estimates."""
        if not rows:
            return
        with self._lock:
            now_ms = self.now_ms()
            self.friction_map.add_station(rows, now_ms)
            self._warnings_out(self.warning_engine.station_evidence(rows, now_ms), ", roadside station")

    def _warnings_out(self, events: list, source: str) -> None:
        """Warning changes stored (the DENM for readers, the event itself to restore the engine after a restart; one
        transaction), counted, logged (raised and ended at WARNING; a refresh, every low pass in a warned cell, at
        DEBUG) and their DENMs published."""
        denms = [event.to_denm() for event in events]
        self.storage.put_warnings([{"warning_id": e.warning_id, "cell": e.cell, "status": e.status,
                                    "detection_ms": e.detection_ms, "updated_ms": e.updated_ms,
                                    "message": {"denm": d, "event": dataclasses.asdict(e)}}
                                   for e, d in zip(events, denms)])
        for event in events:
            self.warning_changes[_change(event)] += 1
            log.log(logging.DEBUG if event.sequence_number and event.status == "active" else logging.WARNING,
                    "warning %s %s in cell %s (%s%s)", event.warning_id, event.status, event.cell, event.reason, source)
        if self.publish is not None:
            for denm in denms:
                self.publish(WARNINGS_TOPIC, orjson.dumps(denm))
