"""serve's intake of edge vehicles' MQTT messages (CONTRACTS 3.7: observations and heartbeats): a bounded queue and one
worker thread that stores them in group transactions and hands the new observations to the fan-out in batches.

- The MQTT handler (`submit`, on paho's network thread) only puts the message on the queue; it never waits. The
  queue holds MAX_EDGE_BACKLOG messages, ten times the service's Receive Maximum (SERVICE_RECEIVE_MAXIMUM,
  roadgrip/cloud/transport/mqtt.py): a broker that keeps to it never fills the queue, even with what a dropped
  connection left in it. One that does not (Mosquitto 2.0.11 after the first PUBACK) can: the handler then raises
  `Busy` and the message stays unacknowledged in the broker, as does every message after it until all that waited is
  stored and acknowledged (`has_room`); then the MQTT client reconnects and the broker delivers the deferred ones
  again (few duplicates: what waited was acknowledged first; a PUBACK still unwritten at the reconnect, or one that
  raced it, makes its message come twice, stored once). paho's thread goes on reading and answering pings meanwhile.
  Memory is bounded by the queue (a message is under `max_payload_bytes`; an observation about 0.5 kB) and a batch.
- The worker takes what waits, up to MAX_EDGE_BATCH messages (it does not wait to fill a batch: alone, a message is
  stored at once; under load, what came in while the previous batch was stored forms the next), parses each (a
  message that breaks the format is reported on the vehicle's errors topic and acknowledged: it would never pass),
  and hands the valid ones to `store` (CloudService.edge_messages: one transaction for the batch's observations and
  heartbeats, then one call of the fan-out). Each message is acknowledged (PUBACK) only after that.
- Exactly once: the tables are keyed by (vehicle_id, last_ms) and (vehicle_id, timestamp_ms) and `store` keeps the
  first of each key within a batch; a message stored whose PUBACK was lost (a dropped connection, a restart) comes
  again and is a duplicate, counted and not fanned out. After a restart the map is restored from the stored
  observations, so one stored before a crash and never fanned out still reaches the map.
- Storage down: the batch is left unacknowledged (logged); the broker delivers it again after the next reconnect.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable

from roadgrip.cloud.api.backend import EdgeIngest
from roadgrip.cloud.ingest.observations import ObservationError, parse_edge_message
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import StorageUnavailable
from roadgrip.cloud.transport.mqtt import SERVICE_RECEIVE_MAXIMUM, Busy

log = logging.getLogger(__name__)

# Messages waiting for the worker: ten of the broker's windows (module docstring), some 10 MB of observations, 11 s of
# docs/EDGE.md's soak. On Mosquitto 2.0.11, which sends past the window, this is what absorbs a stall of the worker:
# past it every message waiting in the broker comes again after the reconnect (the 600 s soak with 4,000 deferred
# within a minute, and the repeated redeliveries took over the service).
MAX_EDGE_BACKLOG = 10 * SERVICE_RECEIVE_MAXIMUM
MAX_EDGE_BATCH = SERVICE_RECEIVE_MAXIMUM // 2  # messages stored in one transaction

Store = Callable[[list[dict], list[dict]], tuple[EdgeIngest, EdgeIngest]]  # (observations, heartbeats) -> results
Rejecter = Callable[[str, list[dict]], None]  # (vehicle_id, rejections)
_STOP = object()


class EdgeIntake:
    """The queue and its worker (module docstring). `clock` (callable() -> s since the epoch): the server's time for
    the parsers' future check."""

    def __init__(
        self,
        settings: Settings,
        store: Store,
        reject: Rejecter,
        max_backlog: int = MAX_EDGE_BACKLOG,
        max_batch: int = MAX_EDGE_BATCH,
        clock=time.time,
    ):
        if max_backlog < 1 or max_batch < 1:
            raise ValueError(f"need max_backlog >= 1 and max_batch >= 1, got {max_backlog!r} and {max_batch!r}")
        self.settings = settings
        self.store = store
        self.reject = reject
        self.max_batch = max_batch
        self.clock = clock
        self._queue: queue.Queue = queue.Queue(max_backlog)
        self._thread: threading.Thread | None = None
        self._deferring = False  # the queue was full: every message is deferred until has_room()
        self._in_hand = False  # the worker holds a batch not yet acknowledged
        # counted by the worker alone (health: pipeline.edge)
        self.counts = dict.fromkeys(
            (
                "observations_received",
                "observations_stored",
                "observations_duplicates",
                "heartbeats_received",
                "heartbeats_stored",
                "heartbeats_duplicates",
                "messages_rejected",
                "batches",
                "largest_batch",
                "batches_failed",
            ),
            0,
        )

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="edge-intake", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Store what waits, then end the worker (call it once the MQTT handler no longer submits)."""
        if self._thread is None:
            return
        self._queue.put(_STOP)
        self._thread.join()
        self._thread = None

    def submit(self, vehicle_id: str, kind: str, payload: bytes, ack: Callable[[], None]) -> None:
        """An MQTT message on an edge vehicle's observations or heartbeat topic (the broker's ACL made sure it is that
        vehicle's). Raises Busy when the queue is full (backpressure, module docstring); never waits."""
        if self._deferring:
            raise Busy("edge intake: deferring until what waits is stored")
        try:
            self._queue.put_nowait((vehicle_id, kind, payload, ack))
        except queue.Full:
            self._deferring = True
            raise Busy(f"edge intake: {self._queue.maxsize} messages wait") from None

    def has_room(self) -> bool:
        """Whether deferred messages may come again: once the queue was full, only when all that waited is stored and
        acknowledged (so the reconnect brings back only the deferred messages, no duplicates); the handler takes
        messages again from then on."""
        if not self._deferring:
            return True
        if self._queue.qsize() or self._in_hand:
            return False
        self._deferring = False
        return True

    @property
    def backlog(self) -> int:
        """Messages waiting for the worker."""
        return self._queue.qsize()

    def stats(self) -> dict:
        return {**self.counts, "backlog": self.backlog}

    def _run(self) -> None:
        stopping = False
        while not stopping:
            batch = [self._queue.get()]
            self._in_hand = True
            while len(batch) < self.max_batch:
                try:
                    batch.append(self._queue.get_nowait())
                except queue.Empty:
                    break
            if _STOP in batch:
                stopping = True
                batch = [m for m in batch if m is not _STOP]
                batch += self._drain()
            for k in range(0, len(batch), self.max_batch):
                try:
                    self._handle(batch[k : k + self.max_batch])
                except Exception:  # the worker must outlive one bad batch: it stays unacknowledged
                    self.counts["batches_failed"] += 1
                    log.exception("edge intake: a batch of %d messages failed; left unacknowledged", len(batch))
            self._in_hand = False

    def _drain(self) -> list:
        rest = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return rest
            if item is not _STOP:
                rest.append(item)

    def _handle(self, batch: list[tuple]) -> None:
        s = self.settings
        now_ms = int(self.clock() * 1000)
        observations, heartbeats, acks = [], [], []
        for vehicle_id, kind, payload, ack in batch:
            try:
                parsed = parse_edge_message(kind, payload, vehicle_id=vehicle_id, settings=s, now_ms=now_ms)
                (observations if kind == "observations" else heartbeats).extend(parsed)
            except ObservationError as exc:
                self.counts["messages_rejected"] += 1
                self.reject(vehicle_id, [exc.to_dict()])
                ack()
                continue
            acks.append(ack)
        if observations or heartbeats:
            try:
                done_observations, done_heartbeats = self.store(observations, heartbeats)
            except StorageUnavailable as exc:
                self.counts["batches_failed"] += 1
                log.warning("edge intake: storage unavailable, %d messages left unacknowledged: %s", len(acks), exc)
                return
            c = self.counts
            c["observations_received"] += done_observations.received
            c["observations_stored"] += done_observations.stored
            c["observations_duplicates"] += done_observations.duplicates
            c["heartbeats_received"] += done_heartbeats.received
            c["heartbeats_stored"] += done_heartbeats.stored
            c["heartbeats_duplicates"] += done_heartbeats.duplicates
        for ack in acks:
            ack()
        self.counts["batches"] += 1
        self.counts["largest_batch"] = max(self.counts["largest_batch"], len(batch))
