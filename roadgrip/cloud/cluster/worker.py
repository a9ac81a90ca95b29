"""A cluster worker (`roadgrip worker`, issue 17 item 2): consumes the partition queues of RabbitMQ
(roadgrip/cloud/transport/amqp.py), runs the vehicles' estimators and stores telemetry and estimates in PostgreSQL, through
the same admission, pipeline, estimator, checkpoints and storage as `roadgrip serve` (roadgrip/cloud/ingest/admission.py,
pipeline.py); only how messages arrive and who owns which vehicles differ.

- Ownership: every worker registers a consumer on every partition queue; single-active-consumer makes one of them
  active per queue, and when its channel or connection dies (the worker killed, its broker node killed) RabbitMQ makes
  another registered consumer active. The first worker to register is active on every partition; the others wait.
- Spreading partitions (`_beat`, a thread of its own): RabbitMQ 3.10 gives a queue to the first consumer registered
  (consumer priorities do not choose the single active consumer of a quorum queue there), so workers hand partitions
  over themselves. Live workers are counted in PostgreSQL: every WATCH_S a worker
  raises its heartbeat counter and reads everyone's (roadgrip/cloud/cluster/spread.py `Liveness`: live while it
  moved within a lease), not from the broker, whose consumer counts a dead node leaves stale (issue 25). The rule of
  spread.py (`Spread`: more than its share of the partitions, the settle time, one move a MOVE_INTERVAL_S, none of a
  partition taken lately, none again while a released partition came back) picks the partition to release,
  the one it took last: the worker stops handing that queue's deliveries to the pipeline, waits until what it handed
  over is stored and acknowledged, lets the pipeline store those vehicles' states and forget them
  (`Pipeline.hand_over`), closes that connection (the next waiting consumer becomes active; what was delivered and
  not taken goes back to the queue) and registers again, at the end of the waiting list. A worker that receives a
  partition it does not need passes it on the same way, to the next in that queue's waiting list.
- One connection per partition (a thread each), to the node `partition mod len(brokers)` of the worker's list, the
  next one after a failure: a dead node costs only the partitions consumed through it.
- A message is an MQTT publish as the broker's MQTT plugin forwarded it: the routing key is the topic with '/' and '.'
  swapped, the body the vehicle's payload. The vehicle is the one of the topic (the broker's topic permissions made
  sure the publisher is that vehicle); `Ingest.mqtt_message` parses it as serve does and queues its samples.
- Acknowledgement after storing: a delivery's tag is done when the pipeline's round that stored its samples committed
  (or at once for a message refused whole); every FLUSH_S the consumer thread takes what the broker sent since in one
  pass of pika's loop and acknowledges, with one multiple-ack, up to the highest tag below which every tag is done, so
  a message is never acknowledged before an earlier one of its queue. A delivery the pipeline has no room for
  (`Busy`: MAX_MQTT_BACKLOG samples wait) waits in the consumer, unacknowledged, with every later one of its queue,
  until the pipeline has room again.
  Per-vehicle order: a queue delivers in order, except to the next consumer after a hand-over (RabbitMQ 3.10's quorum
  queues return the previous consumer's unacknowledged messages out of order: results/trials/cluster/
  handover_order.py); the pipeline takes submissions in order, holds a vehicle it takes over for TAKEOVER_HOLD_S
  (pipeline.py) and its reorder buffer estimates each vehicle's samples in time order.
- Fencing (a partial handover: a worker whose connection died through a dead node, or that has not noticed yet,
  still holds rounds of that partition while the new owner starts on the redelivered messages): the first delivery
  on a partition's channel takes the partition in the database (`Storage.take_partition`: its epoch + 1); every
  round's write carries the epochs of its vehicles' partitions and fails in the same transaction if one was taken
  since (`Fenced`). The worker then drops that partition's rows from the round and writes the rest, acknowledges
  nothing more on that channel, and gives it up (re-registering as a standby). A partition whose connection is lost
  is fenced at once, without asking the database. So a vehicle's estimates are stored by one owner at a time, in
  order.
- Vehicles taken over: the pipeline meets a vehicle for the first time and goes on from its stored estimator state
  (roadgrip/cloud/pipeline/checkpoints.py), estimating only its samples after its newest stored estimate (`skip_estimated`:
  the redelivered ones before it were estimated by the previous owner, and may be in the restored calibration); when
  a partition's connection is lost the worker forgets that partition's vehicles, so that it restores them afresh from
  the database should the partition come back to it.
- Checkpoints every 60 s of a vehicle's data and at a clean stop (SIGTERM, SIGINT): the worker stops taking new
  deliveries (they stay unacknowledged), lets the pipeline store what it took and every vehicle's state, acknowledges,
  then closes its connections: what it did not take goes back to the queues, in order, for the next owner.
- After a round is stored, its estimates go out on the vehicles' friction topics and to the region stage, and the
  round's deliveries are acknowledged only once its region messages are confirmed (roadgrip/cloud/cluster/regions.py
  `WorkerFanout`); every worker also consumes the region queues (`RegionOwners`: the map and the warnings by region)
  and the edge vehicles' queue (roadgrip/cloud/cluster/edge.py `EdgeConsumer`).
- Rejected samples are published, as serve does, on the vehicle's MQTT errors topic (through amq.topic).

Size: over 500 lines because the docstring states the ownership, acknowledgement and fencing protocol the code
implements, next to it.
"""

from __future__ import annotations

import functools
import itertools
import json
import logging
import os
import socket
import threading
import time

import pika
import pika.exceptions

from roadgrip.cloud.cluster.edge import EdgeConsumer
from roadgrip.cloud.cluster.regions import RegionOwners, WorkerFanout
from roadgrip.cloud.cluster.spread import Liveness, Spread
from roadgrip.cloud.cluster.worker_metrics import serve_metrics
from roadgrip.cloud.ingest.admission import Ingest, WaitingLine
from roadgrip.cloud.metrics import LATENCY_BUCKETS_S, BatchHistogram
from roadgrip.cloud.pipeline.pipeline import Pipeline, StoredSink
from roadgrip.cloud.process import warm_up
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Fenced, Storage, StorageUnavailable, Written, open_storage
from roadgrip.cloud.transport.amqp import MQTT_EXCHANGE, declare_topology, mqtt_routing_key, partition_queue
from roadgrip.cloud.transport.amqp_client import BrokersUnreachable, check_brokers, connect, consume
from roadgrip.cloud.transport.mqtt import Busy, errors_topic, vehicle_of_topic
from roadgrip.estimators.learned import load_estimator

log = logging.getLogger(__name__)

# Unacknowledged messages a partition's consumer holds. A delivery is acknowledged a round trip after it came (the
# reorder window, a round, its write, the region confirms: 1-3 s under load), so a worker keeps up with at most
# partitions x prefetch / round trip messages a second: at 100 its 8 partitions capped it near 400 messages (4,000
# samples) a second (docs/CLUSTER.md, "The raw path's cost per worker core"). Deliveries beyond the pipeline's
# MAX_MQTT_BACKLOG wait in the consumer, unacknowledged and unparsed (`Busy`), until it has room.
DEFAULT_PREFETCH = 500
FLUSH_S = 0.05  # how often a consumer thread takes deliveries, hands them over and acknowledges what was stored
STATS_S = 10.0  # how often the worker logs its counters
WATCH_S = 1.0  # how often a worker beats, counts the live workers and checks its share; and reads the queues' depth
MOVE_INTERVAL_S = 1.0  # a worker releases at most one partition in this time
HANDOVER_TIMEOUT_S = 30.0  # a release not done by then (storage down) gives the partition up unacknowledged


class _PartitionLost(Exception):
    """A partition's channel was fenced (another worker took the partition), or its hand-over did not finish."""


class _Acks:
    """Delivery tags of one channel (1, 2, 3, ...): marked done from any thread, acknowledged in order; the
    partition's epoch while this channel holds it; fenced: nothing more is acknowledged or stored."""

    def __init__(self):
        self._lock = threading.Lock()
        self._done: set[int] = set()
        self.acknowledged = 0  # every tag up to this one is acknowledged
        self.epoch: int | None = None  # taken at the channel's first delivery
        self.taken_at = 0.0  # when (monotonic s)
        self.delivered = 0  # the last tag delivered
        self.handed = 0  # the last tag handed to the pipeline
        self.releasing = False  # the partition is being handed over: no more deliveries are taken
        self.fenced = False

    def done(self, tag: int) -> None:
        with self._lock:
            self._done.add(tag)

    def fence(self) -> None:
        with self._lock:
            self.fenced = True

    def flush(self, channel) -> None:
        """One multiple-ack up to the highest tag below which all are done (none if the next is not, or fenced)."""
        with self._lock:
            if self.fenced:
                return
            upto = self.acknowledged
            while upto + 1 in self._done:
                upto += 1
                self._done.discard(upto)
        if upto > self.acknowledged:
            channel.basic_ack(upto, multiple=True)
            self.acknowledged = upto


class _PartitionHold:
    """A partition queue as one consumer connection holds it (an attempt of roadgrip/cloud/transport/amqp_client.py
    `consume`): its acknowledgements, the vehicles delivered through it and the deliveries the pipeline had no room
    for yet (`waiting`, in order: (tag, routing key, body)); `Worker._serve` and `Worker._ended` do the work."""

    def __init__(self, worker: Worker, partition: int):
        self.worker = worker
        self.partition = partition
        self.acks = _Acks()
        self.vehicles: set[str] = set()
        self.waiting: WaitingLine[tuple[int, str, bytes]] = WaitingLine(
            worker.ingest.has_room, functools.partial(worker._hand, self)
        )

    def run(self, connection: pika.BlockingConnection) -> None:
        self.worker._serve(self, connection)

    def ended(self, exc: BaseException | None, broker: int) -> None:
        self.worker._ended(self, exc, broker)


class _Watcher:
    """The worker's connection that counts the live workers and reads the queues' depth (an attempt of `consume`);
    `Worker._watch_through` does the work."""

    def __init__(self, worker: Worker):
        self.worker = worker

    def run(self, connection: pika.BlockingConnection) -> None:
        self.worker._watch_through(connection)

    def ended(self, exc: BaseException | None, broker: int) -> None:
        if exc is not None:
            log.warning("watcher: connection through broker %d lost: %r", broker, exc)


class _Timed:
    """The pipeline's sink in a worker: each stored estimate's latency from its sample's time into the worker's
    histogram (metrics), then on to `sink`."""

    def __init__(self, latency: BatchHistogram, sink: StoredSink):
        self.latency = latency
        self.sink = sink

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        if estimates:
            self.latency.add([(stored_ms - e["timestamp_ms"]) / 1000.0 for e in estimates])
        self.sink.stored(estimates, stored_ms, newest_data_ms)

    def tick(self, final: bool) -> None:
        self.sink.tick(final)


class _FencedStorage:
    """The pipeline's storage in a worker: the worker's Storage, whose `write_batch` and `put_estimator_states` are
    fenced with the epochs of the partitions the rows' vehicles came from (module docstring)."""

    def __init__(self, storage: Storage, worker: Worker):
        self._storage = storage
        self._worker = worker

    def __getattr__(self, name: str):
        return getattr(self._storage, name)

    def write_batch(self, telemetry: list[dict], estimates: list[dict]) -> Written:
        """Write what this worker still owns; the rows of partitions taken from it are left out, and their telemetry
        counted as stored before (their submitters' acknowledgements go to a fenced channel, which sends none)."""
        partition_of = self._worker.partition_of
        written, stale = self._owned(
            lambda fences, t, e: self._storage.write_batch(t, e, fences=fences), telemetry, estimates
        )
        dropped = frozenset(
            (row["vehicle_id"], row["timestamp_ms"]) for row in telemetry if partition_of[row["vehicle_id"]] in stale
        )
        if written is None:
            return Written(0, 0, dropped)
        return Written(written.telemetry, written.estimates, written.already_stored | dropped)

    def put_estimator_states(self, rows: list[dict]) -> None:
        """Store the states of the vehicles whose partitions this worker still owns; the others are left out (their
        new owner's states must not be overwritten by this worker's older ones)."""
        self._owned(lambda fences, r: self._storage.put_estimator_states(r, fences=fences), rows)

    def _owned(self, write, *tables: list[dict]):
        """`write(fences, *tables)` with the epochs of the rows' partitions. The rows of partitions this worker no
        longer holds (fenced, lost, handed over) are left out; a partition found taken by another worker is fenced
        here, its rows left out, and the rest written again. Returns what `write` returned (None when nothing was
        left to write) and the partitions left out."""
        partition_of = self._worker.partition_of
        stale_all: set[int] = set()
        while True:
            acks = {
                p: self._worker.channel_acks(p)
                for p in {partition_of[row["vehicle_id"]] for row in itertools.chain(*tables)}
            }
            stale = {p for p, a in acks.items() if a is None or a.fenced or a.epoch is None}
            if not stale:
                try:
                    return write({p: a.epoch for p, a in acks.items()}, *tables), stale_all
                except Fenced as exc:
                    stale = exc.partitions
                    self._worker.fence(stale)
            stale_all |= stale
            tables = tuple([row for row in rows if partition_of[row["vehicle_id"]] not in stale] for rows in tables)
            if not any(tables):
                return None, stale_all


class Worker:
    """Consumes `partitions` partition queues through the brokers' AMQP URLs (module docstring)."""

    def __init__(self, brokers: list[str], settings: Settings, partitions: int, prefetch: int = DEFAULT_PREFETCH):
        check_brokers(brokers)
        if not isinstance(partitions, int) or partitions < 1:
            raise ValueError(f"partitions must be a positive integer, got {partitions!r}")
        if not isinstance(prefetch, int) or prefetch < 1:
            raise ValueError(f"prefetch must be a positive integer, got {prefetch!r}")
        if settings.database_url is None:
            raise ValueError("settings.database_url must name the shared database (postgresql://...), got None")
        self.brokers = brokers
        self.settings = settings
        self.partitions = partitions
        self.prefetch = prefetch
        self.storage = None
        self.ingest: Ingest | None = None
        self.fanout: WorkerFanout | None = None
        self.regions: RegionOwners | None = None
        self.edge: EdgeConsumer | None = None
        self.rejected = 0
        self.deferred = 0  # hand-overs the pipeline had no room for (Busy): the delivery waited, unacknowledged
        self.deliveries = [0] * partitions  # messages delivered to this worker, per partition
        self.connected = [False] * partitions  # a consumer registered, per partition
        self.lost = 0  # partition connections lost
        self.fenced = 0  # rounds' writes that found a partition taken by another worker
        self.live_workers: int | None = None  # by their heartbeats (this one included), read every WATCH_S
        self.liveness = Liveness()
        self.messages_ready: list[int | None] = [None] * partitions  # each partition queue's, read every WATCH_S
        self.latency_histogram = BatchHistogram(LATENCY_BUCKETS_S)  # sample time to stored estimate (metrics)
        self.owner = f"{socket.gethostname()}:{os.getpid()}"  # its name in partition_owners
        self.spread = Spread(partitions, "partition", self.owner, MOVE_INTERVAL_S)  # its share of the partitions
        self.partition_of: dict[str, int] = {}  # vehicle -> the partition it arrives on (fixed by the hash)
        self._acks: list[_Acks | None] = [None] * partitions  # each partition's current channel
        self._taking = threading.Event()  # deliveries go to the pipeline (cleared at a stop)
        self._closing = threading.Event()
        self._registered = [threading.Event() for _ in range(partitions)]
        self._release = [threading.Event() for _ in range(partitions)]  # set by _watch, done by the consumer
        self._threads: list[threading.Thread] = []
        self._channel = threading.local()  # the consumer thread's channel, for rejections

    def start(self, ready_timeout_s: float = 60.0) -> None:
        """Open the database and the pipeline, declare the topology, register a consumer on every partition; returns
        once all are registered (TimeoutError after `ready_timeout_s`)."""
        s = self.settings
        self.storage = open_storage(s.database_url)
        estimator = load_estimator(s.estimator)
        warm_up(estimator)
        self.fanout = WorkerFanout(self.brokers, s, self.owns)  # friction topics; estimates to their regions
        pipeline = Pipeline(
            _FencedStorage(self.storage, self),
            s,
            estimator,
            _Timed(self.latency_histogram, self.fanout),
            skip_estimated=True,
        )
        self.ingest = Ingest(s, pipeline, reject=self._reject)
        self._declare()
        self.ingest.start()
        self._taking.set()
        for p in range(self.partitions):
            thread = threading.Thread(target=self._consume, args=(p,), name=f"partition-{p}", daemon=True)
            thread.start()
            self._threads.append(thread)
        deadline = time.monotonic() + ready_timeout_s
        for event in self._registered:
            if not event.wait(max(0.0, deadline - time.monotonic())):
                raise TimeoutError(
                    f"not every partition consumer registered within {ready_timeout_s} s: {self.connected}"
                )
        for target, name in ((self._watch, "watch"), (self._beat, "heartbeat")):
            thread = threading.Thread(target=target, name=name, daemon=True)
            thread.start()
            self._threads.append(thread)
        self.regions = RegionOwners(
            self.brokers,
            s,
            self.storage,
            self.owner,  # the map and warnings by region
            live_workers=lambda: self.live_workers,
        )
        self.regions.start(max(1.0, deadline - time.monotonic()))
        self.edge = EdgeConsumer(self.brokers, s, self.storage)  # edge vehicles' MQTT messages (edge.py)
        self.edge.start(max(1.0, deadline - time.monotonic()))
        log.info(
            "worker consuming %d partitions through %d broker(s), estimator %s, storage %s",
            self.partitions,
            len(self.brokers),
            s.estimator,
            self.storage,
        )

    def _declare(self) -> None:
        """Declare the topology through the first broker of the list that answers."""
        try:
            connection, _ = connect(self.brokers)
        except BrokersUnreachable as exc:
            raise ConnectionError(f"declaring the topology: {exc}") from exc
        try:
            declare_topology(connection.channel(), self.partitions, self.settings.region_queues)
        finally:
            connection.close()

    def stop(self) -> None:
        """Stop taking deliveries, store what was taken and every vehicle's estimator state, acknowledge it, close."""
        self._taking.clear()
        if self.ingest is not None:
            self.ingest.stop()
        if self.fanout is not None:
            self.fanout.close()
        self._closing.set()
        for thread in self._threads:
            thread.join(30)
        self._threads = []
        if self.regions is not None:
            self.regions.stop()
        if self.edge is not None:
            self.edge.stop()
        log.info("worker stopped: %s", json.dumps(self.stats()))
        if self.storage is not None:
            try:
                self.storage.end_heartbeat(self.owner)  # counted dead at once by the others
            except StorageUnavailable as exc:
                log.warning("heartbeat not deleted (counted dead a lease later): %s", exc)
            self.storage.close()
            self.storage = None

    def stats(self) -> dict:
        return {
            "partitions_connected": sum(self.connected),
            "partitions_held": self.held_partitions(),
            "live_workers": self.live_workers,
            "moves": self.spread.moves,
            "deliveries": list(self.deliveries),
            "connections_lost": self.lost,
            "fenced": self.fenced,
            "rejected": self.rejected,
            "deferred": self.deferred,
            **(self.fanout.stats() if self.fanout is not None else {}),
            **(self.regions.stats() if self.regions is not None else {}),
            **(self.edge.stats() if self.edge is not None else {}),
            **(self.ingest.stats() if self.ingest is not None else {}),
        }

    def channel_acks(self, partition: int) -> _Acks | None:
        return self._acks[partition]

    def owns(self, vehicle_id: str) -> bool:
        """Whether this worker still holds the vehicle's partition (its estimates go on to the regions)."""
        acks = self._acks[self.partition_of[vehicle_id]]
        return acks is not None and not acks.fenced

    def unacknowledged(self, partition: int) -> int:
        """Messages of the partition delivered to this worker's current channel and not yet acknowledged."""
        acks = self._acks[partition]
        return 0 if acks is None or not self.connected[partition] else acks.delivered - acks.acknowledged

    def held_partitions(self) -> list[int]:
        """The partitions this worker is the active consumer of (it took them: a delivery came), not being released."""
        return [
            p
            for p, a in enumerate(self._acks)
            if a is not None and a.epoch is not None and not a.fenced and not a.releasing and self.connected[p]
        ]

    def fence(self, partitions: set[int]) -> None:
        """Partitions taken by another worker: their channels acknowledge nothing more and are given up."""
        self.fenced += 1
        log.warning(
            "partitions %s were taken by another worker: their rows are dropped, their channels given up",
            sorted(partitions),
        )
        for p in partitions:
            acks = self._acks[p]
            if acks is not None:
                acks.fence()

    # ------------------------------------------------------------------------------------------------- consumers
    def _consume(self, partition: int) -> None:
        """A partition's consumer, through broker `partition` mod the brokers first (roadgrip/cloud/transport/
        amqp_client.py `consume`): connect, register, hand deliveries over and acknowledge until the stop; after a
        failure forget the partition's vehicles and register again through the next broker."""
        consume(
            self.brokers,
            partition,
            self._closing,
            functools.partial(_PartitionHold, self, partition),
            f"partition {partition}",
            (StorageUnavailable, _PartitionLost),
        )

    def _serve(self, hold: _PartitionHold, connection: pika.BlockingConnection) -> None:
        """Register on the partition queue and serve it until the stop or a release (then the caller closes the
        connection: a consumer that released the partition registers again, at the end of the list)."""
        partition, acks = hold.partition, hold.acks
        try:
            channel = connection.channel()
            channel.basic_qos(prefetch_count=self.prefetch)
            self._release[partition].clear()
            self._acks[partition] = acks
            self._channel.channel = channel
            channel.basic_consume(partition_queue(partition), functools.partial(self._on_message, hold))
            self.connected[partition] = True
            self._registered[partition].set()
            while not self._closing.is_set():
                # what the broker sent since the last pass, dispatched in one pass: one wake-up, one ack a FLUSH_S
                connection.process_data_events(time_limit=0)
                if acks.fenced:
                    raise _PartitionLost("taken by another worker")
                self._hand_waiting(hold)
                acks.flush(channel)
                if self._release[partition].is_set():
                    self._hand_over(partition, connection, channel, acks, hold.vehicles)
                    break
                self._closing.wait(FLUSH_S)
            acks.flush(channel)
        except (pika.exceptions.AMQPError, OSError, StorageUnavailable, _PartitionLost):
            acks.fence()  # given up: nothing it took may be stored or acknowledged any more (before the close)
            raise

    def _ended(self, hold: _PartitionHold, exc: BaseException | None, broker: int) -> None:
        """The partition's connection closed: released or stopped (exc None), or given up: what it holds goes back
        to the queue, and its vehicles are forgotten."""
        try:
            if exc is None:
                return
            hold.acks.fence()  # (done already, unless the close itself failed)
            if self._closing.is_set():
                return
            self.lost += 1
            log.warning(
                "partition %d: connection through broker %d lost (%r); forgetting its %d vehicles",
                hold.partition,
                broker,
                exc,
                len(hold.vehicles),
            )
            for vehicle_id in hold.vehicles:  # another worker may own them meanwhile: restore them if they come back
                self.ingest.forget_vehicle(vehicle_id, drop_queued=True)
        finally:
            self.connected[hold.partition] = False

    def _on_message(self, hold: _PartitionHold, channel, method, properties, body: bytes) -> None:
        partition, acks = hold.partition, hold.acks
        acks.delivered = method.delivery_tag
        if not self._taking.is_set() or acks.fenced or acks.releasing:
            return  # stopping, given up or handed over: left unacknowledged, it goes back to the queue at the close
        if acks.epoch is None:  # the channel's first delivery: this consumer is the partition's active one
            acks.epoch = self.storage.take_partition(partition, self.owner)
            acks.taken_at = time.monotonic()
            log.info("partition %d taken, epoch %d", partition, acks.epoch)
        hold.waiting.offer((method.delivery_tag, method.routing_key, body))

    def _hand_waiting(self, hold: _PartitionHold) -> None:
        """Hand the deliveries that waited for room over, in order, once the pipeline has room again (`has_room`:
        its backlog down to half its bound); they stay unacknowledged meanwhile."""
        acks = hold.acks
        if not (acks.fenced or acks.releasing or not self._taking.is_set()):
            hold.waiting.drain()

    def _hand(self, hold: _PartitionHold, delivery: tuple[int, str, bytes]) -> bool:
        """A delivery (tag, routing key, body) to the pipeline; False when it has no room (`Busy`: the delivery
        waits, unacknowledged)."""
        partition, acks = hold.partition, hold.acks
        tag, routing_key, body = delivery
        vehicle_id = vehicle_of_topic(mqtt_routing_key(routing_key))
        if vehicle_id is None:
            log.warning("partition %d: a message with routing key %r names no vehicle; dropped", partition, routing_key)
        else:
            hold.vehicles.add(vehicle_id)
            self.partition_of[vehicle_id] = partition
            try:
                self.ingest.mqtt_message(vehicle_id, body, self.fanout.gate(functools.partial(acks.done, tag)))
            except Busy:
                self.deferred += 1
                return False
        acks.handed = tag
        self.deliveries[partition] += 1
        if vehicle_id is None:
            acks.done(tag)
        return True

    def _hand_over(self, partition: int, connection, channel, acks: _Acks, vehicles: set[str]) -> None:
        """Release a partition this worker holds (module docstring, "Spreading partitions"): take no more deliveries,
        wait until what was taken is stored and acknowledged and the pipeline has stored its vehicles' states and
        forgotten them; the caller then closes the connection. _PartitionLost if that is not done within
        HANDOVER_TIMEOUT_S (the partition is then given up as after a fence)."""
        started = time.monotonic()
        acks.releasing = True
        while acks.acknowledged < acks.handed:
            if self._closing.is_set():
                return  # the worker stops: what was stored is acknowledged by the caller, the rest goes back
            if acks.fenced or time.monotonic() - started > HANDOVER_TIMEOUT_S:
                raise _PartitionLost(f"hand-over: {acks.handed - acks.acknowledged} deliveries not stored")
            connection.process_data_events(time_limit=FLUSH_S)
            acks.flush(channel)
        states = self.ingest.pipeline.hand_over(vehicles)
        while not states.done():
            if self._closing.is_set():
                return  # the worker stops: its pipeline stored every state
            if time.monotonic() - started > HANDOVER_TIMEOUT_S:
                raise _PartitionLost("hand-over: the vehicles' states were not stored")
            connection.process_data_events(time_limit=FLUSH_S)
        log.info(
            "partition %d released: %d deliveries stored and acknowledged, the states of %d vehicles stored, in %.2f s",
            partition,
            acks.acknowledged,
            states.result(),
            time.monotonic() - started,
        )

    # ------------------------------------------------------------------------------------------------- spreading
    def _watch(self) -> None:
        """Every WATCH_S read the partition queues' depth (metrics). After a failure, the same through the next
        broker."""
        consume(self.brokers, 0, self._closing, functools.partial(_Watcher, self), "watcher")

    def _watch_through(self, connection: pika.BlockingConnection) -> None:
        channel = connection.channel()
        while not self._closing.is_set():
            for p in range(self.partitions):
                self.messages_ready[p] = channel.queue_declare(partition_queue(p), passive=True).method.message_count
            connection.process_data_events(time_limit=WATCH_S)

    def _beat(self) -> None:
        """Every WATCH_S raise this worker's heartbeat, count the live workers by theirs (spread.py `Liveness`) and
        release a partition when this worker holds more than its share (`_balance`). The database down: the count
        is not known (None), and nothing moves."""
        while not self._closing.is_set():
            now = time.monotonic()
            try:
                self.storage.heartbeat(self.owner)
                self.live_workers = self.liveness.count(now, self.storage.worker_heartbeats())
                for owner, beats in self.liveness.dead_rows(now).items():
                    self.storage.end_heartbeat(owner, beats)
            except StorageUnavailable as exc:
                self.live_workers = None
                log.warning("heartbeat: %s", exc)
            self._balance(now)
            self._closing.wait(WATCH_S)

    def _balance(self, now: float) -> None:
        """Release the partition taken last if this worker holds more than its share (roadgrip/cloud/cluster/
        spread.py)."""
        if any(e.is_set() for e in self._release):
            return
        held = {p: self._acks[p].taken_at for p in self.held_partitions()}
        try:
            partition = self.spread.release(now, self.live_workers, held, self.storage.partition_owners)
        except StorageUnavailable as exc:
            log.warning("partition owners not read (tried again in %.0f s): %s", WATCH_S, exc)
            return
        if partition is not None:
            self._release[partition].set()

    def _reject(self, vehicle_id: str, errors: list[dict]) -> None:
        """Rejections of a message (called by Ingest.mqtt_message in the consumer's thread): counted, logged,
        published on the vehicle's errors topic."""
        self.rejected += len(errors)
        log.warning("rejected %d sample(s) from vehicle %s: %s", len(errors), vehicle_id, errors[0]["reason"])
        self._channel.channel.basic_publish(
            MQTT_EXCHANGE,
            mqtt_routing_key(errors_topic(vehicle_id)),
            json.dumps({"vehicle_id": vehicle_id, "rejected": errors}).encode(),
        )


def run_worker(
    brokers: list[str],
    settings: Settings,
    partitions: int,
    prefetch: int = DEFAULT_PREFETCH,
    stop: threading.Event | None = None,
    metrics_port: int | None = None,
    metrics_host: str = "127.0.0.1",
) -> None:
    """Run a worker until `stop` is set (the command sets it on SIGTERM or SIGINT), logging its counters every
    STATS_S; with `metrics_port`, its Prometheus metrics at http://metrics_host:metrics_port/metrics
    (roadgrip/cloud/cluster/worker_metrics.py)."""
    stop = stop or threading.Event()
    worker = Worker(brokers, settings, partitions, prefetch)
    worker.start()
    server = None
    try:
        if metrics_port is not None:
            server = serve_metrics(worker, metrics_port, metrics_host)
            log.info("metrics at http://%s:%d/metrics", metrics_host, server.server_port)
        while not stop.wait(STATS_S):
            log.info("worker: %s", json.dumps(worker.stats()))
    finally:
        if server is not None:
            server.shutdown()
            server.server_close()
        worker.stop()
