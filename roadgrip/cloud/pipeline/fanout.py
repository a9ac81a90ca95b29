"""What follows once a round's estimates are stored (step 6 of roadgrip/cloud/pipeline/pipeline.py), in two parts that
both modes run:

- per vehicle (`VehicleFanout`), where the vehicle's estimates are stored: the latency from a sample's own time to its
  stored estimate (health: `latency`, `latency_since_start`), and each vehicle's estimates published together on its
  friction topic, one message (a JSON array) per `friction_publish_interval_s`; the round's estimates then go on to
  the regions;
- per region (`RegionFanout`): the friction map and the warning engine take the estimates (and roadside stations'
  evidence, and edge vehicles' observations as the rows of their passes), warning changes are stored and their DENMs
  published at once (JSON and UPER, each on its topic).

`roadgrip serve` has one `Fanout`, in its main process: its vehicles' part, and one region that holds everything (the
map and the warnings need every vehicle there): the pipeline calls it in the same process, and with
`ingest_processes` the pipelines of the ingest processes send it what they stored (roadgrip/cloud/serve/shards.py).
Calls from several threads are serialised by one lock. In cluster mode (issue 17 item 3) a worker runs the vehicles'
part for the vehicles it owns and hands the estimates to the region owners through the broker
(roadgrip/cloud/cluster/regions.py), each of which runs one RegionFanout per region (H3 parent cell) it met.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from typing import Protocol

import numpy as np
import orjson

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.observations import pass_rows
from roadgrip.cloud.domain.warnings import ACTIVE, EXPIRED, WarningEngine
from roadgrip.cloud.formats.denm import denm, denm_uper
from roadgrip.cloud.metrics import LATENCY_BUCKETS_S, BatchHistogram
from roadgrip.cloud.pipeline.latency import LatencyRecorder
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage
from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, WARNINGS_UPER_TOPIC, friction_topic
from roadgrip.data.schema import ESTIMATE_FIELDS

log = logging.getLogger(__name__)

WARNING_CHANGES = ("raised", "refreshed", "cancelled", "expired")


def estimate_message(row: dict) -> dict:
    return {k: row[k] for k in ESTIMATE_FIELDS}


def _change(event) -> str:
    """A warning event as one of WARNING_CHANGES (roadgrip/cloud/domain/warnings.py: status, reason, sequence_number)."""
    if event.status == ACTIVE:
        return "refreshed" if event.sequence_number else "raised"
    return "expired" if event.reason == EXPIRED else "cancelled"


def new_friction_map(settings: Settings, **overrides) -> FrictionMap:
    """The friction map of the settings (resolution, half-life, age limit, the warnings' pass gap: one pass rule for
    both, roadgrip/cloud/domain/passes.py), as serve and the region owners build it; `overrides`: FrictionMap
    arguments that replace the settings' (a study's). The one Settings-to-map mapping."""
    return FrictionMap(
        **{
            "resolution": settings.h3_resolution,
            "half_life_s": settings.map_half_life_s,
            "max_age_s": settings.map_max_age_s,
            "pass_gap_s": settings.warning_pass_gap_s,
            **overrides,
        }
    )


def new_warning_engine(settings: Settings, action_sequence=None, **overrides) -> WarningEngine:
    """The warning engine of the settings, as serve and the region owners build it; `action_sequence` as WarningEngine
    takes it; `overrides`: WarningEngine arguments that replace the settings' (the fleet benchmark's sweep). The one
    Settings-to-engine mapping."""
    return WarningEngine(
        **{
            "resolution": settings.h3_resolution,
            "threshold_mu": settings.warning_threshold_mu,
            "min_low_passes": settings.warning_min_low_passes,
            "min_dry_passes": settings.warning_min_dry_passes,
            "pass_gap_s": settings.warning_pass_gap_s,
            "min_excited_per_pass": settings.warning_min_excited_per_pass,
            "validity_s": settings.warning_validity_s,
            "station_id": settings.station_id,
            "action_sequence": action_sequence,
            **overrides,
        }
    )


class RegionSink(Protocol):
    """Where a vehicles' part hands a stored round's estimates: a RegionFanout, or the publisher to the region
    owners (roadgrip/cloud/cluster/regions.py)."""

    def estimates(self, rows: list[dict], newest_data_ms: int) -> None:
        """A round's estimates (rows with at least ESTIMATE_FIELDS) and its newest sample's timestamp."""


class WarningsStore(Protocol):
    """Where a region's warning changes are stored: Storage, or a region owner's fenced writer."""

    def put_warnings(self, rows: list[dict]) -> None:
        """Store (or replace) warnings, one transaction."""


class VehicleFanout:
    """The per-vehicle part (module docstring). Not thread-safe: one caller (serve's Fanout holds a lock around it; a
    worker's pipeline thread)."""

    def __init__(self, settings: Settings, regions: RegionSink, publish=None, clock=time.monotonic):
        self.settings = settings
        self.regions = regions
        self.publish = publish  # callable(topic, payload bytes) or None
        self.clock = clock  # callable() -> s, monotonic: when an estimate was queued, when it is due
        self.latency = LatencyRecorder()  # sample time to stored estimate
        self.latency_histogram = BatchHistogram(LATENCY_BUCKETS_S)  # the same, in seconds, for the metrics
        self.busy_s = 0.0  # seconds spent in `stored` since start
        # vehicle -> (when its oldest unpublished estimate was queued, monotonic s; the estimate messages)
        self._outbox: dict[str, tuple[float, list[dict]]] = {}

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        """A round was stored at `stored_ms` (ms since epoch) with these estimates; its newest sample's timestamp."""
        started = time.perf_counter()
        if estimates:
            latencies_ms = stored_ms - np.fromiter((e["timestamp_ms"] for e in estimates), float, len(estimates))
            self.latency.add(latencies_ms)
            self.latency_histogram.add(latencies_ms / 1000.0)
        self.regions.estimates(estimates, newest_data_ms)
        if estimates and self.publish is not None:
            now_s = self.clock()
            for row in estimates:
                self._outbox.setdefault(row["vehicle_id"], (now_s, []))[1].append(estimate_message(row))
        self.busy_s += time.perf_counter() - started

    def tick(self, final: bool = False) -> None:
        """Publish the estimates of each vehicle whose oldest unpublished one waited friction_publish_interval_s
        (all of them when `final`). Called after every round."""
        if not self._outbox:
            return
        due_since = self.clock() - self.settings.friction_publish_interval_s
        due = [v for v, (since, _) in self._outbox.items() if final or since <= due_since]
        for vehicle_id in due:
            self.publish(friction_topic(vehicle_id), orjson.dumps(self._outbox.pop(vehicle_id)[1]))


class RegionFanout:
    """The per-region part (module docstring): one region's map and warning engine, its warning changes stored in
    `store` and their DENMs published. Its clock (`now_ms`): the server's, or with map_clock "data" the newest sample
    of the rounds it was given. Not thread-safe: one caller at a time."""

    def __init__(
        self,
        store: WarningsStore,
        settings: Settings,
        friction_map: FrictionMap,
        warning_engine: WarningEngine,
        publish=None,
        clock=time.time,
    ):
        self.store = store
        self.settings = settings
        self.friction_map = friction_map
        self.warning_engine = warning_engine
        self.publish = publish  # callable(topic, payload bytes) or None
        self.clock = clock  # callable() -> s since the epoch: the server's clock (map_clock "wall")
        self.warning_changes = dict.fromkeys(WARNING_CHANGES, 0)  # warning events by change (metrics)
        self.newest_data_ms = 0

    def now_ms(self) -> int:
        """The clock for the map and warnings: the server's, or the newest stored sample's (`map_clock`)."""
        if self.settings.map_clock == "data":
            return self.newest_data_ms
        return int(self.clock() * 1000)

    def estimates(self, rows: list[dict], newest_data_ms: int) -> set[str]:
        """A round's estimates into the map and the warning engine; warning changes out. The map cells touched."""
        self.newest_data_ms = max(self.newest_data_ms, newest_data_ms)
        if not rows:
            return set()
        now_ms = self.now_ms()
        touched = self.friction_map.add(rows, now_ms)
        self._warnings_out(self.warning_engine.update(rows, now_ms), "")
        return touched

    def station_reports(self, rows: list[dict]) -> set[str]:
        """The evidence of newly stored roadside station reports (roadgrip/cloud/domain/stations.py, evidence_rows:
        one row per covered cell) into the map and the warning engine; warning changes out as after a round of
        estimates. The map cells touched."""
        if not rows:
            return set()
        now_ms = self.now_ms()
        touched = self.friction_map.add_station(rows, now_ms)
        self._warnings_out(self.warning_engine.station_evidence(rows, now_ms), ", roadside station")
        return touched

    def tick(self) -> None:
        """Without new estimates, let the server's clock end passes and expire warnings (a region owner calls it
        about once a second; serve's one region is updated by every round of any vehicle instead). Nothing with the
        data clock, which only data moves."""
        if self.settings.map_clock == "data" or not (
            self.warning_engine.open_passes_ or self.warning_engine.active_cells_
        ):
            return
        now_ms = self.now_ms()
        self.friction_map.add([], now_ms)  # idle passes end in the map as in the engine (domain/passes.py)
        self._warnings_out(self.warning_engine.update([], now_ms), "")

    def _warnings_out(self, events: list, source: str) -> None:
        """Warning changes stored (the DENM for readers, the event itself to restore the engine after a restart; one
        transaction), counted, logged (raised and ended at WARNING; a refresh, every low pass in a warned cell, at
        DEBUG) and their DENMs published, as JSON and UPER-encoded (each on its topic)."""
        denms = [denm(event) for event in events]
        self.store.put_warnings(
            [
                {
                    "warning_id": e.warning_id,
                    "cell": e.cell,
                    "status": e.status,
                    "detection_ms": e.detection_ms,
                    "updated_ms": e.updated_ms,
                    "message": {"denm": d, "event": dataclasses.asdict(e)},
                }
                for e, d in zip(events, denms)
            ]
        )
        for event in events:
            self.warning_changes[_change(event)] += 1
            log.log(
                logging.DEBUG if event.sequence_number and event.status == "active" else logging.WARNING,
                "warning %s %s in cell %s (%s%s)",
                event.warning_id,
                event.status,
                event.cell,
                event.reason,
                source,
            )
        if self.publish is not None:
            for message in denms:
                self.publish(WARNINGS_TOPIC, orjson.dumps(message))
                self.publish(WARNINGS_UPER_TOPIC, denm_uper(message))


class Fanout:
    """serve's fan-out: the vehicles' part and one region holding everything, under one lock (module docstring).
    `clock` (callable() -> s; a test's fake one): both parts read it; by default each its own (time.time for the map
    and warnings, time.monotonic for the publish interval)."""

    def __init__(
        self,
        storage: Storage,
        settings: Settings,
        friction_map: FrictionMap,
        warning_engine: WarningEngine,
        publish=None,
        clock=None,
    ):
        self.storage = storage
        self.settings = settings
        clocks = {} if clock is None else {"clock": clock}
        self.region = RegionFanout(storage, settings, friction_map, warning_engine, publish, **clocks)
        self.vehicles = VehicleFanout(settings, self.region, publish, **clocks)
        # edge vehicles' observations: from the end of the pass (last_ms; a vehicle sends it then) to the map updated
        self.observation_latency = LatencyRecorder()
        self._lock = threading.Lock()

    @property
    def friction_map(self) -> FrictionMap:
        return self.region.friction_map

    @property
    def warning_engine(self) -> WarningEngine:
        return self.region.warning_engine

    @property
    def latency(self) -> LatencyRecorder:
        return self.vehicles.latency

    @property
    def latency_histogram(self) -> BatchHistogram:
        return self.vehicles.latency_histogram

    @property
    def warning_changes(self) -> dict[str, int]:
        return self.region.warning_changes

    @property
    def busy_s(self) -> float:
        """Seconds spent in `stored` since start (health: pipeline.fanout_s)."""
        return self.vehicles.busy_s

    def now_ms(self) -> int:
        """The service's clock for the map and warnings: the server's, or the newest stored sample's (`map_clock`)."""
        return self.region.now_ms()

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        """A round was stored at `stored_ms` (ms since epoch) with these estimates; its newest sample's timestamp."""
        with self._lock:
            self.vehicles.stored(estimates, stored_ms, newest_data_ms)

    def tick(self, final: bool = False) -> None:
        """Publish the estimates of each vehicle whose oldest unpublished one waited friction_publish_interval_s
        (all of them when `final`). Called after every round."""
        with self._lock:
            self.vehicles.tick(final)

    def station_reports(self, rows: list[dict]) -> None:
        """The evidence of newly stored roadside station reports into the map and the warning engine, under the
        lock (RegionFanout.station_reports)."""
        with self._lock:
            self.region.station_reports(rows)

    def observations(self, observations: list[dict]) -> None:
        """Newly stored friction observations of edge vehicles (CONTRACTS 3.7) into the map and the warning engine as
        the passes they stand for (roadgrip/cloud/domain/observations.py), under the lock, like a round's estimates: a
        batch of them in one call. Then each one's latency from its last_ms to the map updated (the region's clock;
        health: `observation_latency`)."""
        if not observations:
            return
        rows = [row for o in observations for row in pass_rows(o)]
        last_ms = np.fromiter((o["last_ms"] for o in observations), float, len(observations))
        with self._lock:
            self.region.estimates(rows, int(last_ms.max()))
            self.observation_latency.add(self.region.clock() * 1000.0 - last_ms)
