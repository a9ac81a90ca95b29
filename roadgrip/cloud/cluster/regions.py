"""The region fan-out of cluster mode (issue 17 item 3): the friction map and the warnings are computed per region, an H3
parent cell at `region_resolution` (Settings), by whichever worker owns that region's queue, fed by a second keyed
stage, not by one process that sees everything. The same code as serve's fan-out (roadgrip/cloud/pipeline/fanout.py):
`VehicleFanout` where a vehicle's estimates are stored, `RegionFanout` per region.

The stage (roadgrip/cloud/transport/amqp.py): the x-consistent-hash exchange rg.estimates over M quorum queues with
single-active-consumer, rg.estimates.r0 .. rM-1 (M = Settings.region_queues), declared with the partition queues.

Worker side (`WorkerFanout`, the pipeline's sink in `roadgrip worker`):
- after a round is stored, each vehicle's estimates are published on its friction topic, as serve does
  (`VehicleFanout`, through amq.topic, which the MQTT plugin delivers to MQTT subscribers), and the round's estimates
  with a position go to rg.estimates, one message per region (routing key: the region cell; body: JSON
  {"newest_data_ms": the round's newest sample, "estimates": [estimate messages, ESTIMATE_FIELDS]}), each with
  publisher confirms;
- the telemetry deliveries of a round are acknowledged only after its region messages are confirmed (`gate`): the
  pipeline resolves a round's deliveries before handing it on, so the worker's acknowledgements wait in `gate` until
  the round's publishes are confirmed (or, for a round with nothing to publish, until the next `tick`);
- estimates of vehicles whose partition this worker lost (fenced) are not published: the partition's new owner
  estimates those samples again.

Region side (`RegionOwners`, started by every worker): a consumer on every region queue (one connection each, to the
(q mod count)-th broker, the next after a failure); the active one of each queue takes it in the database
(`Storage.take_region_queue`: an epoch, as partitions) at its first delivery and keeps, per region it meets, a
RegionFanout (`Regions`): on meeting a region it restores its map cells (roadgrip/cloud/cluster/map_cells.py) and its
active warnings from the database. Every SAVE_S it lets the server's clock end passes and expire warnings
(`RegionFanout.tick`), saves the cells changed since (`Storage.put_region_output`, fenced by the queue's epoch: a stale
owner stores nothing once another has taken the queue) and then acknowledges the messages applied: a message is
acknowledged only once what it changed in the map is stored; warning changes are stored as they happen (fenced too),
and their DENMs published on the MQTT warnings topic through amq.topic. When its connection fails or a write is fenced
the consumer forgets the queue's regions and registers again: a region that comes back is restored afresh. The first
worker to register is active on every queue; region queues are then spread over the live workers as partitions are
(`RegionOwners._spread`): a worker holding more than its share releases the queue it took last (cancel, save,
acknowledge, close, register again), and the next waiting consumer takes it and restores its regions.

Guarantees and their limits (docs/CLUSTER.md, "Region fan-out (item 3)"):
- Estimates stored and confirmed reach their region at least once. A region drops an estimate of a vehicle not newer
  than the newest it applied of that vehicle (estimates of a vehicle are made in time order, once: the pipeline
  estimates a sample after the newest stored estimate only), and after a takeover not newer than the newest of that
  vehicle in the restored cells, so a redelivered message counts once in the map. The broker returns the previous
  owner's unacknowledged messages out of order (results/trials/cluster/handover_order.py): a queue's new owner holds
  what it is delivered in its first TAKEOVER_HOLD_S (pipeline.py) and applies it per region as one message, its
  estimates in time order (`Regions.apply_held`), so a vehicle's older estimates are not dropped behind newer ones.
- Crash window: a worker that stored a round and died before its publish was confirmed leaves the round's telemetry
  unacknowledged; the partition's next owner stores nothing new of it and estimates none of it again
  (`skip_estimated`), so those estimates never reach the region (they are in the database; the map misses them).
- The warning engine's state besides its active warnings (passes in progress, low passes not yet enough to raise, the
  last dry pass) is not saved: a region that moves loses it, as serve's restart does.
- A vehicle's pass that crosses a region border ends in the first region only when that region's clock passes
  pass_gap_s beyond it (serve's one map ends it when the vehicle is seen in the next cell).
- With map_clock "data" each region's clock is the newest sample of the rounds that reached it (serve: of every round).

Size: over 500 lines because the region stage's two sides (the worker's publisher and the region owners' consumers)
share one message format and one fencing protocol.
"""

from __future__ import annotations

import functools
import logging
import threading
import time
from collections.abc import Callable

import orjson
import pika

from roadgrip.cloud.cluster.map_cells import cell_rows, restore_region
from roadgrip.cloud.cluster.spread import Spread
from roadgrip.cloud.domain.cells import region_of
from roadgrip.cloud.domain.observations import pass_rows
from roadgrip.cloud.domain.warnings import WarningEvent
from roadgrip.cloud.pipeline.fanout import (
    WARNING_CHANGES,
    RegionFanout,
    VehicleFanout,
    estimate_message,
    new_friction_map,
    new_warning_engine,
)
from roadgrip.cloud.pipeline.pipeline import TAKEOVER_HOLD_S
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Fenced, Storage, StorageUnavailable
from roadgrip.cloud.transport.amqp import ESTIMATES_EXCHANGE, MQTT_EXCHANGE, mqtt_routing_key, region_queue
from roadgrip.cloud.transport.amqp_client import ConfirmedPublisher, check_brokers, consume

log = logging.getLogger(__name__)

SPREAD_WATCH_S = 1.0  # how often a region owner checks its share of the region queues
MOVE_INTERVAL_S = 3.0  # a worker releases at most one region queue in this time
SAVE_S = 1.0  # how often a region owner saves the changed cells and acknowledges (so: at most once a second a cell)
CLEANUP_S = 60.0  # how often it deletes its regions' cells older than map_max_age_s from the database
REGION_PREFETCH = 1000  # unacknowledged region messages per queue: more than SAVE_S of them must fit
FLUSH_S = 0.05  # a region consumer's wait for deliveries between its checks of the save timer
JSON = pika.BasicProperties(content_type="application/json", delivery_mode=2)


def check_region_resolution(settings: Settings) -> int:
    """The region resolution, which must be at most the map's (a region is a parent of map cells)."""
    if settings.region_resolution > settings.h3_resolution:
        raise ValueError(
            f"region_resolution must be at most h3_resolution ({settings.h3_resolution}), got "
            f"{settings.region_resolution}"
        )
    return settings.region_resolution


class RegionPublisher(ConfirmedPublisher):
    """Region messages to rg.estimates with publisher confirms, and MQTT topics through amq.topic without, through the
    brokers' AMQP URLs (roadgrip/cloud/transport/amqp_client.py `ConfirmedPublisher`: one connection at a time, the
    next broker after a failure, one lock for all threads); a worker uses it from its pipeline's thread only."""

    def __init__(self, brokers: list[str]):
        super().__init__(brokers, what="region publisher")

    def publish_region(self, region: str, body: bytes, deadline_s: float | None = None) -> None:
        """Publish one message to rg.estimates keyed by `region` and wait for its confirm, through the next broker
        after a failure, until confirmed, or with `deadline_s` until then (TimeoutError; `ConfirmedPublisher.publish`
        says how the deadline is counted). RuntimeError once `close` was called and it is still not confirmed."""
        self.publish(
            ESTIMATES_EXCHANGE, region, [body], JSON, deadline_s=deadline_s, what=f"region message for {region}"
        )

    def publish_mqtt(self, topic: str, payload: bytes) -> None:
        """Publish on an MQTT topic through amq.topic, without a confirm: at most once (a vehicle's estimates, as
        serve drops them when its broker is behind; they are stored)."""
        self.publish_unconfirmed(MQTT_EXCHANGE, mqtt_routing_key(topic), payload)


def publish_station_evidence(
    publisher: RegionPublisher, rows: list[dict], region_resolution: int, deadline_s: float | None = None
) -> int:
    """Hand the evidence of stored roadside station reports (roadgrip/cloud/domain/stations.py `evidence_rows`:
    station_id, cell, timestamp_ms, mu, mu_lower, mu_upper; one row per covered cell) to the owners of their cells'
    regions: one confirmed message per region, all of them within `deadline_s` of the call (TimeoutError, as
    RegionPublisher.publish_region; the regions published before stay published). Returns the messages published. The
    stations route of `roadgrip api` calls it after `Storage.put_station_reports`."""
    started = time.monotonic()
    by_region: dict[str, list[dict]] = {}
    for row in rows:
        by_region.setdefault(region_of(row["cell"], region_resolution), []).append(row)
    for region, group in sorted(by_region.items()):
        left_s = None if deadline_s is None else deadline_s - (time.monotonic() - started)
        publisher.publish_region(region, orjson.dumps({"stations": group}), left_s)
    return len(by_region)


def publish_observations(
    publisher: RegionPublisher, observations: list[dict], region_resolution: int, deadline_s: float | None = None
) -> int:
    """Hand the rows of the passes of edge vehicles' observations (roadgrip/cloud/domain/observations.py `pass_rows`,
    oldest observation first) to the owners of their regions as a round's estimates go (`region_messages`): one
    confirmed message per region, all within `deadline_s` of the call (TimeoutError, as
    RegionPublisher.publish_region). A region applies a vehicle's rows once (`Regions.apply`), so observations
    handed on again (stored before, a redelivery) count once. Returns the messages published. Callers: the API's
    observations route (roadgrip/cloud/cluster/api_backend.py), the MQTT consumer (roadgrip/cloud/cluster/edge.py)."""
    if not observations:
        return 0
    started = time.monotonic()
    rows = [row for o in sorted(observations, key=lambda o: o["last_ms"]) for row in pass_rows(o)]
    messages = region_messages(rows, max(o["last_ms"] for o in observations), region_resolution)
    for region, message in messages.items():
        left_s = None if deadline_s is None else deadline_s - (time.monotonic() - started)
        publisher.publish_region(region, orjson.dumps(message), left_s)
    return len(messages)


def region_messages(rows: list[dict], newest_data_ms: int, region_resolution: int) -> dict[str, dict]:
    """A round's estimate rows (with h3_cell) as the region stage's messages, by region, in region order: {"newest_data_ms",
    "estimates": [estimate messages]}. Rows without a cell (no position) go to no region."""
    by_region: dict[str, list[dict]] = {}
    for row in rows:
        if row["h3_cell"] is not None:
            by_region.setdefault(region_of(row["h3_cell"], region_resolution), []).append(estimate_message(row))
    return {region: {"newest_data_ms": newest_data_ms, "estimates": by_region[region]} for region in sorted(by_region)}


class WorkerFanout:
    """The pipeline's sink in a worker (module docstring): a vehicle's estimates on its friction topic, a round's
    estimates to their regions with confirms, the round's deliveries acknowledged after (`gate`). `owns(vehicle_id)`:
    whether this worker still holds the vehicle's partition. Called from the pipeline's thread (`gate` from any)."""

    def __init__(self, brokers: list[str], settings: Settings, owns: Callable[[str], bool]):
        self.settings = settings
        self.region_resolution = check_region_resolution(settings)
        self.publisher = RegionPublisher(brokers)
        self.vehicles = VehicleFanout(settings, self, self.publisher.publish_mqtt)
        self.owns = owns
        self.region_messages = 0
        self.window_s_max = 0.0  # longest time from a round's commit to its region messages' last confirm
        self._pending: list[Callable[[], None]] = []  # acknowledgements waiting for the round's confirms
        self._lock = threading.Lock()

    def gate(self, ack: Callable[[], None]) -> Callable[[], None]:
        """`ack` to be called once the round that stores the delivery has been confirmed by the region stage."""
        return functools.partial(self._hold, ack)

    def _hold(self, ack: Callable[[], None]) -> None:
        with self._lock:
            self._pending.append(ack)

    def _release(self, acks: list[Callable[[], None]]) -> None:
        for ack in acks:
            ack()

    def _take_pending(self) -> list[Callable[[], None]]:
        with self._lock:
            pending, self._pending = self._pending, []
        return pending

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        """A round stored (the pipeline resolved its deliveries just before): publish, then acknowledge. The time
        from the round's commit to its last confirm is the crash window (module docstring); its longest is kept."""
        ready = self._take_pending()
        self.vehicles.stored(estimates, stored_ms, newest_data_ms)
        self.window_s_max = max(self.window_s_max, time.time() - stored_ms / 1000.0)
        self._release(ready)

    def estimates(self, rows: list[dict], newest_data_ms: int) -> None:
        """The RegionSink of `vehicles`: one confirmed message per region of the round's estimates with a cell."""
        messages = region_messages(
            [row for row in rows if self.owns(row["vehicle_id"])], newest_data_ms, self.region_resolution
        )
        for region, message in messages.items():
            self.publisher.publish_region(region, orjson.dumps(message))
        self.region_messages += len(messages)

    def tick(self, final: bool = False) -> None:
        """After every round: friction messages due, acknowledgements of deliveries with nothing to publish,
        heartbeats."""
        self.vehicles.tick(final)
        self._release(self._take_pending())
        self.publisher.idle()

    def close(self) -> None:
        """After the pipeline stopped: close the publisher's connection."""
        self.publisher.close()

    def stats(self) -> dict:
        return {
            "region_messages_published": self.region_messages,
            "region_publish_failures": self.publisher.failures,
            "region_publish_window_s_max": round(self.window_s_max, 4),
        }


class _FencedWrites:
    """A region queue's writes, fenced by its epoch (None: unfenced)."""

    def __init__(self, storage: Storage, fence: tuple[int, int] | None):
        self.storage = storage
        self.fence = fence

    def put_warnings(self, rows: list[dict]) -> None:
        self.storage.put_region_output(rows, [], self.fence)


class Regions:
    """The regions an owner holds (one region queue's, or any set): a RegionFanout per region, restored from the
    database when first met; the cells changed since the last `save`. Not thread-safe."""

    def __init__(self, settings: Settings, storage: Storage, publish=None, fence: tuple[int, int] | None = None):
        self.settings = settings
        self.region_resolution = check_region_resolution(settings)
        self.storage = storage
        self.publish = publish  # callable(topic, payload bytes) or None
        self.writes = _FencedWrites(storage, fence)
        self.held: dict[str, RegionFanout] = {}
        self.dropped = 0  # estimates not newer than their vehicle's newest in the region (repeats)
        self._newest: dict[str, dict[str, int]] = {}  # region -> vehicle -> newest estimate applied (or restored)
        self._dirty: dict[str, set[str]] = {}  # region -> cells changed since saved
        self._cleaned_at = time.monotonic()

    def region(self, region: str) -> RegionFanout:
        """The region's fan-out; restored from the database (map cells, active warnings) when first met."""
        fanout = self.held.get(region)
        if fanout is None:
            fanout = self.held[region] = self._restore(region)
        return fanout

    def _restore(self, region: str) -> RegionFanout:
        fmap = new_friction_map(self.settings)
        cells = restore_region(fmap, self.storage, region)
        engine = new_warning_engine(self.settings, self.storage.next_action_sequence_number)
        active = [
            WarningEvent(**row["message"]["event"])
            for row in self.storage.warnings(active_only=True)
            if region_of(row["cell"], self.region_resolution) == region
        ]
        engine.restore(active)
        newest: dict[str, int] = {}
        for cell in fmap.cells_by_id_.values():
            for vehicle, t in cell.vehicles.items():
                newest[vehicle] = max(t, newest.get(vehicle, t))
        self._newest[region] = newest
        self._dirty[region] = set()
        log.info("region %s met: restored %d map cells and %d active warnings", region, cells, len(active))
        return RegionFanout(self.writes, self.settings, fmap, engine, self.publish)

    def apply(self, region: str, message: dict) -> None:
        """A message of the region stage: {"newest_data_ms", "estimates": [...]} or {"stations": [...]}."""
        fanout = self.region(region)
        touched: set[str] = set()
        if "estimates" in message:
            newest = self._newest[region]
            rows = []
            for row in message["estimates"]:
                vehicle, t = row["vehicle_id"], row["timestamp_ms"]
                if t <= newest.get(vehicle, -1):
                    self.dropped += 1
                    continue
                newest[vehicle] = t
                rows.append(row)
            touched |= fanout.estimates(rows, int(message["newest_data_ms"]))
        if "stations" in message:
            touched |= fanout.station_reports(message["stations"])
        self._dirty[region] |= touched

    def apply_held(self, held: list[tuple[str, dict]]) -> None:
        """Messages held at a takeover (routing key, message), in the order delivered: per region as one message, its
        estimates in time order (the broker returned the previous owner's out of order: a vehicle's older estimates
        behind newer ones would be dropped as repeats), its station reports in the order delivered."""
        merged: dict[str, dict] = {}
        for region, message in held:
            into = merged.setdefault(region, {})
            if "estimates" in message:
                into["newest_data_ms"] = max(int(message["newest_data_ms"]), into.get("newest_data_ms", 0))
                into.setdefault("estimates", []).extend(message["estimates"])
            if "stations" in message:
                into.setdefault("stations", []).extend(message["stations"])
        for region, message in merged.items():
            if "estimates" in message:
                message["estimates"].sort(key=lambda row: row["timestamp_ms"])
            self.apply(region, message)

    def tick(self) -> None:
        for fanout in self.held.values():
            fanout.tick()

    def save(self) -> int:
        """Store the cells changed since the last save (one transaction, fenced); every CLEANUP_S also delete the
        held regions' cells whose evidence is older than map_max_age_s. How many cells were stored."""
        rows = [
            row
            for region, cells in self._dirty.items()
            if cells
            for row in cell_rows(self.held[region].friction_map, cells, self.region_resolution)
        ]
        self.storage.put_region_output([], rows, self.writes.fence)
        for cells in self._dirty.values():
            cells.clear()
        if time.monotonic() - self._cleaned_at >= CLEANUP_S:
            self._cleaned_at = time.monotonic()
            for region, fanout in self.held.items():
                before_ms = int(fanout.now_ms() - self.settings.map_max_age_s * 1000) - fanout.friction_map.bucket_ms
                self.storage.delete_map_cells(region, before_ms, self.writes.fence)
        return len(rows)

    def warning_changes(self) -> dict[str, int]:
        """Warning events of the held regions by change (WARNING_CHANGES); read from any thread."""
        changes = dict.fromkeys(WARNING_CHANGES, 0)
        for fanout in list(self.held.values()):
            for change, n in fanout.warning_changes.items():
                changes[change] += n
        return changes


def _checked(message: dict) -> dict:
    """A region message to hold (`Regions.apply_held`), checked as `Regions.apply` would read it: KeyError, TypeError
    or ValueError if it is not one, so that it is dropped alone, not the messages held with it."""
    if "estimates" in message:
        int(message["newest_data_ms"])
        for row in message["estimates"]:
            row["vehicle_id"], int(row["timestamp_ms"])
    if "stations" in message:
        list(message["stations"])
    return message


class _QueueState:
    """A region queue as one consumer connection holds it (an attempt of roadgrip/cloud/transport/amqp_client.py
    `consume`): its regions once taken (first delivery), the last delivery applied and the last acknowledged."""

    def __init__(self, owners: RegionOwners, q: int):
        self.owners = owners
        self.q = q
        self.regions: Regions | None = None
        self.held: list[tuple[str, dict]] | None = None  # taken: the deliveries of the first TAKEOVER_HOLD_S, in order
        self.hold_until = 0.0  # (monotonic s)
        self.applied = 0  # the last delivery applied, or held
        self.acknowledged = 0

    def run(self, connection: pika.BlockingConnection) -> None:
        self.owners._serve(self.q, self, connection)

    def ended(self, exc: BaseException | None, broker: int) -> None:
        self.owners._ended(self.q, self, exc, broker)


class RegionOwners:
    """Every worker's consumers of the region queues (module docstring). `owner`: its name in region_owners."""

    def __init__(
        self,
        brokers: list[str],
        settings: Settings,
        storage: Storage,
        owner: str,
        live_workers: Callable[[], int | None] | None = None,
    ):
        self.brokers = check_brokers(brokers)
        check_region_resolution(settings)
        self.settings = settings
        self.storage = storage
        self.owner = owner
        self.live_workers = live_workers  # how many workers are live (None: not known); None: queues are not spread
        self.queues = settings.region_queues
        self.held: list[Regions | None] = [None] * self.queues  # each queue's regions while this worker is active
        self.messages = [0] * self.queues  # region messages applied, per queue
        self.lost = 0  # queue connections lost or given up
        self.spread = Spread(self.queues, "region queue", owner, MOVE_INTERVAL_S)  # its share of the queues
        self.cells_saved = 0
        self._warning_changes_before = dict.fromkeys(WARNING_CHANGES, 0)  # of the queues this worker held earlier
        self._held_lock = threading.Lock()  # `held` and `_warning_changes_before` change together (stats' counters)
        self._closing = threading.Event()
        self._registered = [threading.Event() for _ in range(self.queues)]
        self._release = [threading.Event() for _ in range(self.queues)]  # set by _spread, done by the consumer
        self._taken_at = [0.0] * self.queues  # when each queue held was taken (monotonic s)
        self._threads: list[threading.Thread] = []

    def start(self, ready_timeout_s: float = 60.0) -> None:
        """Register a consumer on every region queue; returns once all are registered (TimeoutError after
        `ready_timeout_s`)."""
        for q in range(self.queues):
            thread = threading.Thread(target=self._consume, args=(q,), name=f"region-queue-{q}", daemon=True)
            thread.start()
            self._threads.append(thread)
        deadline = time.monotonic() + ready_timeout_s
        for q, event in enumerate(self._registered):
            if not event.wait(max(0.0, deadline - time.monotonic())):
                raise TimeoutError(f"region queue {q}: no consumer registered within {ready_timeout_s} s")
        if self.live_workers is not None:
            thread = threading.Thread(target=self._watch, name="region-spread", daemon=True)
            thread.start()
            self._threads.append(thread)

    def stop(self) -> None:
        """Save what was applied, acknowledge it, close (the queues go to the next registered consumers)."""
        self._closing.set()
        for thread in self._threads:
            thread.join(30)
        self._threads = []

    def stats(self) -> dict:
        """Counters since this worker started (warning_changes: of every queue it held, a counter for metrics), and
        the region queues and regions it holds now."""
        with self._held_lock:
            held = {q: r for q, r in enumerate(self.held) if r is not None}
            changes = dict(self._warning_changes_before)
            for regions in held.values():
                for change, n in regions.warning_changes().items():
                    changes[change] += n
        return {
            "region_queues_held": list(held),
            "regions_held": sum(len(r.held) for r in held.values()),
            "region_messages_applied": list(self.messages),
            "region_connections_lost": self.lost,
            "region_queue_moves": self.spread.moves,
            "map_cells_saved": self.cells_saved,
            "warning_changes": changes,
        }

    # ----------------------------------------------------------------------------------------- spreading queues

    def _watch(self) -> None:
        while not self._closing.wait(SPREAD_WATCH_S):
            try:
                self._spread(time.monotonic())
            except StorageUnavailable as exc:
                log.warning("region owners not read (tried again in %.0f s): %s", SPREAD_WATCH_S, exc)

    def _spread(self, now: float) -> None:
        """Release the region queue taken last when this worker holds more than its share (the rule of
        roadgrip/cloud/cluster/spread.py, the partitions' own)."""
        if any(e.is_set() for e in self._release):
            return
        held = {q: self._taken_at[q] for q, r in enumerate(self.held) if r is not None}
        q = self.spread.release(now, self.live_workers(), held, self.storage.region_owners)
        if q is not None:
            self._release[q].set()

    def _consume(self, q: int) -> None:
        """A region queue's consumer, through broker q mod the brokers first (roadgrip/cloud/transport/amqp_client.py
        `consume`), until the stop."""
        consume(
            self.brokers,
            q,
            self._closing,
            functools.partial(_QueueState, self, q),
            f"region queue {q}",
            (StorageUnavailable, Fenced),
        )

    def _serve(self, q: int, state: _QueueState, connection: pika.BlockingConnection) -> None:
        """Register on the queue; apply what is delivered, save and acknowledge every SAVE_S, until the stop or a
        release; then cancel, save and acknowledge (the caller closes the connection: the next waiting consumer
        becomes active; a released queue registers again)."""
        channel = connection.channel()
        channel.basic_qos(prefetch_count=REGION_PREFETCH)
        tag = channel.basic_consume(region_queue(q), functools.partial(self._on_message, q, state))
        self._registered[q].set()
        next_save = time.monotonic() + SAVE_S
        while not self._closing.is_set() and not self._release[q].is_set():
            connection.process_data_events(time_limit=FLUSH_S)
            if state.held is not None and time.monotonic() >= state.hold_until:
                self._end_hold(q, state)
            if time.monotonic() >= next_save and state.held is None:
                self._save(q, state, channel)
                next_save = time.monotonic() + SAVE_S
        channel.basic_cancel(tag)  # no more deliveries, then what was applied is saved and acknowledged
        self._end_hold(q, state)
        self._save(q, state, channel)

    def _ended(self, q: int, state: _QueueState, exc: BaseException | None, broker: int) -> None:
        """The queue's connection closed: released, or given up (what it held goes back to the queue); either way
        this worker forgets the queue's regions."""
        regions = 0 if state.regions is None else len(state.regions.held)
        try:
            if exc is None:
                if self._release[q].is_set():
                    log.info("region queue %d released: its %d regions saved and acknowledged", q, regions)
                    self._release[q].clear()
            elif not self._closing.is_set():
                self.lost += 1
                log.warning(
                    "region queue %d: given up through broker %d (%r); forgetting its %d regions",
                    q,
                    broker,
                    exc,
                    regions,
                )
        finally:
            with self._held_lock:
                if self.held[q] is not None:
                    for change, n in self.held[q].warning_changes().items():
                        self._warning_changes_before[change] += n
                self.held[q] = None

    def _on_message(self, q: int, state: _QueueState, channel, method, properties, body: bytes) -> None:
        if state.regions is None:  # the channel's first delivery: this consumer is the queue's active one
            epoch = self.storage.take_region_queue(q, self.owner)
            self._taken_at[q] = time.monotonic()
            state.regions = Regions(self.settings, self.storage, functools.partial(self._publish, channel), (q, epoch))
            self.held[q] = state.regions
            state.held, state.hold_until = [], time.monotonic() + TAKEOVER_HOLD_S
            log.info("region queue %d taken, epoch %d", q, epoch)
        try:
            message = orjson.loads(body)
            if state.held is None:
                state.regions.apply(method.routing_key, message)
                self.messages[q] += 1
            else:
                state.held.append((method.routing_key, _checked(message)))
        except (ValueError, KeyError, TypeError):  # never valid: acknowledged with the others, not redelivered
            log.exception(
                "region queue %d: a message for region %r could not be applied; dropped", q, method.routing_key
            )
        state.applied = method.delivery_tag

    def _end_hold(self, q: int, state: _QueueState) -> None:
        """Apply what the first TAKEOVER_HOLD_S of a queue taken delivered (`Regions.apply_held`)."""
        held, state.held = state.held, None
        if not held:
            return
        try:
            state.regions.apply_held(held)
        except (ValueError, KeyError, TypeError):  # as a message's in _on_message: acknowledged, not redelivered
            log.exception("region queue %d: the %d messages held at its takeover could not be applied", q, len(held))
        self.messages[q] += len(held)

    def _save(self, q: int, state: _QueueState, channel) -> None:
        """Close due passes and expire warnings, store the changed cells, then acknowledge what was applied."""
        if state.regions is None:
            return
        state.regions.tick()
        self.cells_saved += state.regions.save()
        if state.applied > state.acknowledged:
            channel.basic_ack(state.applied, multiple=True)
            state.acknowledged = state.applied

    @staticmethod
    def _publish(channel, topic: str, payload: bytes) -> None:
        channel.basic_publish(MQTT_EXCHANGE, mqtt_routing_key(topic), payload)
