"""The per-vehicle streaming pipeline: validated samples in; telemetry and estimates stored, then handed on to the
fan-out (map, warnings, publishing).

One worker thread runs a loop every `flush_interval_s`. Each round it takes what was submitted since the last round,
up to MAX_ROUND_SAMPLES (the rest goes in the next round, at once), and:

1. drops the samples it remembers storing (same vehicle_id and timestamp_ms: a repeated HTTP request or an MQTT
   redelivery; it remembers the last DEDUP_HORIZON_MS of each vehicle) and, inside the round, keeps the first of equal
   timestamps;
2. puts each vehicle's new samples into that vehicle's reorder buffer and releases, in time order, the samples older than
   the vehicle's newest by `reorder_window_s` (all of them once the vehicle has been silent that long): a sample that
   arrives out of order within the window is estimated in its place (a vehicle a cluster worker takes over releases
   nothing for TAKEOVER_HOLD_S: the broker hands the previous owner's messages over out of order);
3. feeds the released samples to the vehicle's estimator (`roadgrip.estimators.base.Estimator`, the interface the offline
   tools use), each vehicle's in one `update_many` (the estimates `update` gives sample by sample, without the
   per-sample Python where the estimator has its own). A gap longer than `max_gap_s` restarts the estimator (`reset`)
   rather than bridging it. A sample older than one already estimated (later than the reorder window allowed) is
   stored but not estimated: counted as `late`;
4. writes the round's new telemetry and its estimates in one transaction, idempotent on (vehicle_id, timestamp_ms):
   the database skips an older repeat, or one stored before a restart, and names the rows it had already;
5. only then resolves the submitters' futures (HTTP answers, MQTT acks) with those counts: an acknowledged sample is
   stored, and counted as stored only when this submission stored it;
6. hands the round's estimates to what follows (`StoredSink`): in the service's process the fan-out
   (roadgrip/cloud/pipeline/fanout.py: the map, warnings, publishing); in an ingest process, the channel to it
   (roadgrip/cloud/serve/shards.py);
7. stores the estimator states of the vehicles that are due (every 60 s of a vehicle's data; at most 25 vehicles in
   one transaction every 0.5 s) and, when it stops, of every vehicle estimated since; a vehicle seen for the first time
   since the start goes on from its stored state where that fits (roadgrip/cloud/pipeline/checkpoints.py): its
   self-calibration survives a restart.

If the database is down (StorageUnavailable), the round is held and retried (backoff up to MAX_RETRY_S) before anything
newer. HTTP submitters get StorageUnavailable at once (503: nothing acknowledged; their samples may still be written
when the database is back, harmlessly, since storing is idempotent); MQTT messages stay unacknowledged and wait, as do
the MQTT messages that arrive meanwhile; the broker stops sending once `receive_maximum` messages are unacknowledged,
which bounds what the service holds. Nothing acknowledged is lost.

Size: over 500 lines because one thread's state machine (reorder window, rounds, the write, hand-over of vehicles) whose
parts share its locks and counters; split, the locking would be spread over modules.
"""

from __future__ import annotations

import heapq
import logging
import math
import threading
import time
from concurrent.futures import Future
from dataclasses import dataclass, field
from typing import Protocol

from roadgrip.cloud.domain.cells import cells_of
from roadgrip.cloud.metrics import ESTIMATOR_BUCKETS_S, BatchHistogram
from roadgrip.cloud.pipeline.checkpoints import Checkpoints
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Storage, StorageUnavailable
from roadgrip.estimators.base import Estimator
from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

log = logging.getLogger(__name__)

# How far back the pipeline remembers stored timestamps per vehicle, to drop repeats before estimating them. An older
# repeat reaches the database, which skips it and says so (Storage.write_batch): the counts stay exact. The memory costs
# up to 2 x 300 timestamps a vehicle at 10 Hz: 52 MB for 1,000 vehicles (tracemalloc); 10 minutes took 717 MB.
DEDUP_HORIZON_MS = 30_000
# The most samples a round takes (whole submissions: the one that reaches it is the last). At 10,000 samples/s a round
# of 0.1 s has 1,000; after a stall the queue holds up to MAX_MQTT_BACKLOG (roadgrip/cloud/ingest/admission.py), and one round of
# it all made every buffer of the round (rows, estimates, the fan-out's messages) that large at once: the memory steps
# at stalls of the soaks in docs/RELIABILITY.md.
MAX_ROUND_SAMPLES = 5_000
SLOW_ROUND_S = 1.0  # a round slower than this is counted (health: pipeline.slow_rounds): the service stalled
MAX_RETRY_S = 2.0  # longest wait between two tries while storage is down (doubling from 0.2 s)
# A vehicle a cluster worker takes over (`skip_estimated`) is estimated only after this long of the clock from its first
# arrival: RabbitMQ 3.10's quorum queues hand the previous consumer's unacknowledged messages to the next one out of
# order (among themselves and with newer ones; 13-15 of 19 hand-overs in results/trials/cluster/handover_order.py),
# all in the first burst, so the reorder buffer puts them back in order within the hold instead of calling them late.
TAKEOVER_HOLD_S = 1.0


class StoredSink(Protocol):
    """Where a pipeline's stored rounds go (roadgrip/cloud/pipeline/fanout.py `Fanout`, or an ingest process's channel)."""

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        """A round was stored at `stored_ms` (ms since epoch) with these estimates; its newest sample's timestamp."""

    def tick(self, final: bool) -> None:
        """Called after every round (`final`: the last one, the pipeline stops)."""


@dataclass(frozen=True)
class SubmitResult:
    stored: int  # samples newly stored
    duplicates: int  # samples already stored before (or twice in the submission)


class VehicleMoved(Exception):
    """A submission dropped because its vehicle's partition went to another worker (`forget_vehicle`)."""


@dataclass
class _Submission:
    vehicle_id: str
    samples: list[dict]
    future: Future
    retry: bool  # may wait while storage is down (MQTT: unacknowledged until stored)


@dataclass
class _Held:
    """A round processed but not yet stored: written before anything newer."""

    results: list  # (submission, timestamps of its samples sent to the database)
    rows: list[dict]
    late: list  # (vehicle_id, timestamp_ms) of samples behind what was estimated: not estimated
    estimates: list[dict]
    touched: set[str]


@dataclass
class _VehicleStream:
    state: object
    pending: list = field(default_factory=list)  # heap of (timestamp_ms, seq, sample)
    newest_ms: int = -1
    last_estimated_ms: int | None = None
    last_arrival_s: float = 0.0
    stored: set = field(default_factory=set)  # timestamps stored within DEDUP_HORIZON_MS of newest_ms
    checkpoint_at_ms: float = math.inf  # data time at which its state is due for a checkpoint (Checkpoints)
    written_ms: int | None = None  # last_estimated_ms of its stored state
    held_until_s: float | None = None  # taken over: nothing released before this (clock), then what was estimated read
    first_ms: float = math.inf  # its oldest sample seen while held


@dataclass
class PipelineCounters:
    submitted: int = 0
    stored: int = 0
    duplicates: int = 0
    late: int = 0
    restarts: int = 0
    estimates: int = 0
    rounds: int = 0
    failed_rounds: int = 0
    last_round_s: float = 0.0
    slowest_round_s: float = 0.0  # since start
    slow_rounds: int = 0  # rounds that took longer than SLOW_ROUND_S
    # seconds spent since start, by part of the round: where a stall went
    estimate_s: float = 0.0  # reorder buffers and the estimator
    write_s: float = 0.0  # the round's transaction (telemetry and estimates)
    checkpoints_written: int = 0  # estimator states stored (roadgrip/cloud/pipeline/checkpoints.py)
    checkpoints_restored: int = 0  # vehicles that went on from a stored estimator state
    checkpoint_s: float = 0.0  # seconds spent storing estimator states

    def to_dict(self) -> dict:
        return dict(vars(self))


class Pipeline:
    """`skip_estimated`: a vehicle first seen is held for TAKEOVER_HOLD_S, then not estimated at or before its newest
    estimate stored from its oldest sample on: those samples are redeliveries of what another owner estimated (and may
    have checkpointed into the state this pipeline restores, whose calibration would count them twice). A cluster
    worker sets it (roadgrip/cloud/cluster/worker.py); `roadgrip serve` does not. `clock` (callable() -> s, monotonic;
    a test's fake one): the reorder window's (when a vehicle's samples arrived), the hold's and the storage retry's
    backoff."""

    def __init__(
        self,
        storage: Storage,
        settings: Settings,
        estimator: Estimator,
        sink: StoredSink,
        skip_estimated: bool = False,
        clock=time.monotonic,
    ):
        self.storage = storage
        self.settings = settings
        self.estimator = estimator
        self.sink = sink
        self.skip_estimated = skip_estimated
        self.clock = clock
        self.counters = PipelineCounters()
        self.estimator_time = BatchHistogram(ESTIMATOR_BUCKETS_S)  # seconds per estimator update (metrics)
        self._inbox: list[_Submission] = []
        self._queued = 0
        self._lock = threading.Lock()
        self._wake = threading.Event()
        self._stop = threading.Event()
        self._streams: dict[str, _VehicleStream] = {}
        self._profiles: dict[str, VehicleParams] = {}
        self._newest_data_ms = 0
        self._seq = 0
        self._forget: set[str] = set()
        self._handovers: list[tuple[set[str], Future]] = []  # vehicles leaving, and who waits for their states
        self._held: _Held | None = None
        self._failures = 0
        self._retry_at = 0.0
        self._thread: threading.Thread | None = None
        self.checkpoints = Checkpoints(storage, estimator, self.counters)

    # ------------------------------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="roadgrip-pipeline", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Process what was submitted, store the estimator states of the vehicles estimated since their last
        checkpoint, then stop."""
        self._stop.set()
        self._wake.set()
        if self._thread is not None:
            self._thread.join(timeout_s)
            self._thread = None

    def submit(self, vehicle_id: str, samples: list[dict], *, retry: bool = False) -> Future:
        """Queue validated samples of one vehicle; the future resolves to a SubmitResult once they are stored. While
        storage is down it fails with StorageUnavailable, unless `retry`: then it waits until they are stored."""
        future: Future = Future()
        if self._stop.is_set():
            future.set_exception(RuntimeError("the pipeline is stopping"))
            return future
        with self._lock:
            self._inbox.append(_Submission(vehicle_id, samples, future, retry))
            self._queued += len(samples)
        return future

    @property
    def backlog(self) -> int:
        """Samples submitted and not yet taken by a round (O(1): the MQTT handler asks for every message)."""
        return self._queued

    @property
    def running(self) -> bool:
        return self._thread is not None and not self._stop.is_set()

    def forget_vehicle(self, vehicle_id: str, drop_queued: bool = False) -> None:
        """Start the vehicle afresh at the next round: its profile is read again (it changed) and its estimator
        restarts. With `drop_queued` (a cluster worker that lost the vehicle's partition: another worker owns it now
        and gets what was submitted of it again), its submissions not yet taken by a round are dropped too, their
        futures failed with VehicleMoved: else the next round would forget the vehicle and then start it again here
        from those older samples, and should the partition come back, its redelivered samples would be behind
        them (late, never estimated). A round already under way finishes first; the forget follows it."""
        with self._lock:
            self._forget.add(vehicle_id)
            dropped = [sub for sub in self._inbox if sub.vehicle_id == vehicle_id] if drop_queued else []
            if dropped:
                self._inbox = [sub for sub in self._inbox if sub.vehicle_id != vehicle_id]
                self._queued -= sum(len(sub.samples) for sub in dropped)
        for sub in dropped:
            if not sub.future.done():
                sub.future.set_exception(VehicleMoved(vehicle_id))

    def hand_over(self, vehicle_ids: set[str]) -> Future:
        """Vehicles that leave this pipeline (a cluster worker gives their partition to another worker,
        roadgrip/cloud/cluster/worker.py): once nothing submitted of theirs waits (in the inbox, a reorder buffer or
        a held round), their estimator states are stored (one transaction) and they are forgotten. The submitter must
        have stopped submitting them. The future resolves to the number of states stored; while storage is down it
        waits."""
        future: Future = Future()
        with self._lock:
            self._handovers.append((set(vehicle_ids), future))
        self._wake.set()
        return future

    # ------------------------------------------------------------------------------------------------- the loop
    def _run(self) -> None:
        while True:
            stopping = self._stop.is_set()
            started = time.perf_counter()
            queued = self._queued
            try:
                self.run_round(final=stopping)
                self.sink.tick(final=stopping)
                self._hand_over_ready()
            except Exception:  # a bug must not kill the service's only worker: log it and go on
                log.exception("pipeline round failed")
            took = self.counters.last_round_s = time.perf_counter() - started
            self.counters.slowest_round_s = max(self.counters.slowest_round_s, took)
            self.counters.slow_rounds += took > SLOW_ROUND_S
            if stopping and not 0 < self._queued < queued:  # all done, or no progress (storage down)
                self._checkpoint_all()
                return
            if self._queued >= MAX_ROUND_SAMPLES:  # behind: the next round at once
                continue
            self._wake.wait(max(0.0, self.settings.flush_interval_s - (time.perf_counter() - started)))
            self._wake.clear()

    def _hand_over_ready(self) -> None:
        """Store the states of the vehicles handed over whose samples are all stored and estimated, and forget them."""
        if not self._handovers or self._held is not None:
            return
        with self._lock:
            waiting = {sub.vehicle_id for sub in self._inbox}
            handovers = list(self._handovers)
        for vehicles, future in handovers:
            if vehicles & waiting or any(self._streams[v].pending for v in vehicles & self._streams.keys()):
                continue  # the reorder buffers release them once the vehicles are silent for reorder_window_s
            written = self.checkpoints.write(sorted(vehicles & self._streams.keys()), self._streams)
            if written is None:
                continue  # storage down: tried again after the next round
            for vehicle_id in vehicles:
                self._profiles.pop(vehicle_id, None)
                self._streams.pop(vehicle_id, None)
            with self._lock:
                self._handovers.remove((vehicles, future))
            future.set_result(written)

    def _checkpoint_all(self) -> None:
        if self.storage_down:
            log.error(
                "storage is down at the stop: the estimator states of %d vehicles were not stored", len(self._streams)
            )
            return
        try:
            self.checkpoints.write_all(self._streams)
        except Exception:
            log.exception("storing the estimator states at the stop failed")

    def run_round(self, final: bool = False) -> None:
        with self._lock:
            taken = count = 0
            while taken < len(self._inbox) and count < MAX_ROUND_SAMPLES:
                count += len(self._inbox[taken].samples)
                taken += 1
            inbox, self._inbox = self._inbox[:taken], self._inbox[taken:]
            self._queued -= count
            forget, self._forget = self._forget, set()
        for vehicle_id in forget:
            self._profiles.pop(vehicle_id, None)
            self._streams.pop(vehicle_id, None)
        if self._held is not None and not self._write_held():
            self._refuse_or_keep(
                inbox, StorageUnavailable("storage is down; the service holds what it acknowledged until it is back")
            )
            return
        now_s = self.clock()
        try:
            for sub in inbox:  # every profile first: a storage failure here leaves nothing half done
                self._profile(sub.vehicle_id)
            self._open_streams(inbox, now_s)
            self._end_holds(inbox, now_s, final)
        except StorageUnavailable as exc:
            self._refuse_or_keep(inbox, exc)
            return
        results: list[tuple[_Submission, list[int]]] = []
        new_rows: list[dict] = []
        touched: set[str] = set()
        for sub in inbox:
            stream = self._streams[sub.vehicle_id]
            seen_now: set[int] = set()
            stored, pending, seq = stream.stored, stream.pending, self._seq
            for sample in sub.samples:
                ts = sample["timestamp_ms"]
                if ts in stored or ts in seen_now:
                    continue
                seen_now.add(ts)
                new_rows.append(sample)
                seq += 1
                heapq.heappush(pending, (ts, seq, sample))
            if seq > self._seq:  # new samples: the vehicle's newest and when it was last heard
                self._seq = seq
                stream.newest_ms = max(stream.newest_ms, max(seen_now))
                stream.last_arrival_s = now_s
            touched.add(sub.vehicle_id)
            results.append((sub, list(seen_now)))
            # a later submission in the same round sees this one's samples as already taken
            stream.stored |= seen_now
        self.counters.rounds += 1
        started = time.perf_counter()
        late: list[tuple[str, int]] = []
        estimates = self._release(now_s, final, late)
        self.counters.estimate_s += time.perf_counter() - started
        self._held = _Held(results, new_rows, late, estimates, touched)
        if self._write_held():
            self.checkpoints.write_due(self._streams)

    def _write_held(self) -> bool:
        """Write the held round (one transaction). On success resolve its submitters and fan out. When storage is
        down, answer the submitters that cannot wait (HTTP: StorageUnavailable, retry) and keep the round for the
        next try, after a backoff, while those that can (MQTT, unacknowledged until stored) wait. Any other failure
        is a bug: every submitter gets it and the round is dropped (logged)."""
        held = self._held
        if self.clock() < self._retry_at:
            return False
        started = time.perf_counter()
        repeats: frozenset[tuple[str, int]] = frozenset()  # rows the database had already
        try:
            if held.rows or held.estimates:
                repeats = self.storage.write_batch(held.rows, held.estimates).already_stored
        except StorageUnavailable as exc:
            self.counters.failed_rounds += 1
            self._failures += 1
            self._retry_at = self.clock() + min(MAX_RETRY_S, 0.1 * 2**self._failures)
            for sub, _ in held.results:
                if not sub.retry and not sub.future.done():
                    sub.future.set_exception(exc)
            if self._failures == 1:
                log.error("storage is down, holding %d samples and retrying: %s", len(held.rows), exc)
            return False
        except Exception as exc:
            self._held = None
            self.counters.failed_rounds += 1
            for sub, timestamps in held.results:  # not stored: a later repeat must be taken
                if sub.vehicle_id in self._streams:
                    self._streams[sub.vehicle_id].stored.difference_update(timestamps)
                if not sub.future.done():
                    sub.future.set_exception(exc)
            log.exception("storing a round of %d samples failed; dropped", len(held.rows))
            return True
        finally:
            self.counters.write_s += time.perf_counter() - started
        if self._failures:
            log.warning(
                "storage is back after %d failed tries; wrote the %d samples held", self._failures, len(held.rows)
            )
        self._held, self._failures, self._retry_at = None, 0, 0.0
        for sub, timestamps in held.results:
            stored = len(timestamps) - (sum((sub.vehicle_id, ts) in repeats for ts in timestamps) if repeats else 0)
            duplicates = len(sub.samples) - stored
            self.counters.stored += stored
            self.counters.duplicates += duplicates
            self.counters.submitted += len(sub.samples)
            if not sub.future.done():
                sub.future.set_result(SubmitResult(stored, duplicates))
        late = [key for key in held.late if key not in repeats]  # a repeat is a duplicate, not late
        if late:
            self.counters.late += len(late)
            vehicle_id, timestamp_ms = min(late)
            log.warning(
                "%d samples stored but not estimated: behind what was estimated (the first: %s at %d, estimated to %s)",
                len(late),
                vehicle_id,
                timestamp_ms,
                self._streams[vehicle_id].last_estimated_ms if vehicle_id in self._streams else "?",
            )
        if held.rows:
            self._newest_data_ms = max(self._newest_data_ms, max(r["timestamp_ms"] for r in held.rows))
        for vehicle_id in held.touched & self._streams.keys():  # a vehicle forgotten meanwhile starts afresh
            self._trim(self._streams[vehicle_id])
        self.counters.estimates += len(held.estimates)
        if held.rows or held.estimates:
            self.sink.stored(held.estimates, time.time() * 1000.0, self._newest_data_ms)
        return True

    def _refuse_or_keep(self, inbox: list[_Submission], exc: Exception) -> None:
        """While storage is down: refuse what cannot wait, keep (in order, ahead of newer ones) what can."""
        keep = []
        for sub in inbox:
            if sub.retry:
                keep.append(sub)
            elif not sub.future.done():
                sub.future.set_exception(exc)
        with self._lock:
            self._inbox = keep + self._inbox
            self._queued += sum(len(sub.samples) for sub in keep)

    @property
    def storage_down(self) -> bool:
        return self._held is not None and self._failures > 0

    # ------------------------------------------------------------------------------------------------- per vehicle
    def _open_streams(self, inbox: list[_Submission], now_s: float) -> None:
        """Streams for the vehicles first seen (their profiles read): from their stored estimator states where those
        fit, else fresh; held for TAKEOVER_HOLD_S with `skip_estimated`. StorageUnavailable leaves nothing half
        done."""
        first_ms: dict[str, float] = {}
        for sub in inbox:
            if sub.vehicle_id not in self._streams:
                first_ms[sub.vehicle_id] = min(
                    first_ms.get(sub.vehicle_id, math.inf),
                    min((s["timestamp_ms"] for s in sub.samples), default=math.inf),
                )
        if not first_ms:
            return
        states = self.checkpoints.start_states({v: self._profiles[v] for v in first_ms})
        for vehicle_id, state in states.items():
            self._streams[vehicle_id] = _VehicleStream(
                state,
                checkpoint_at_ms=self.checkpoints.first_due_ms(vehicle_id, first_ms[vehicle_id]),
                held_until_s=now_s + TAKEOVER_HOLD_S if self.skip_estimated else None,
            )

    def _end_holds(self, inbox: list[_Submission], now_s: float, final: bool) -> None:
        """The vehicles taken over whose hold ends: estimated only after their newest estimate stored from their
        oldest sample seen on (those are redeliveries of what another owner estimated, and may be in the restored
        state, whose calibration would count them twice)."""
        for sub in inbox:
            stream = self._streams[sub.vehicle_id]
            if stream.held_until_s is not None:
                stream.first_ms = min(stream.first_ms, min((s["timestamp_ms"] for s in sub.samples), default=math.inf))
        for vehicle_id, stream in self._streams.items():
            if stream.held_until_s is None or not (final or now_s >= stream.held_until_s):
                continue
            if stream.first_ms < math.inf:
                stored = self.storage.estimates(vehicle_id, start_ms=int(stream.first_ms))
                if stored:
                    stream.last_estimated_ms = stored[-1]["timestamp_ms"]
            stream.held_until_s = None

    def _profile(self, vehicle_id: str) -> VehicleParams:
        params = self._profiles.get(vehicle_id)
        if params is None:
            profile = self.storage.vehicle_profile(vehicle_id)
            params = PAPER_SUV if profile is None else VehicleParams.from_dict(profile)
            self._profiles[vehicle_id] = params
        return params

    def _trim(self, stream: _VehicleStream) -> None:
        """Remember DEDUP_HORIZON_MS of timestamps; an older repeat reaches the database, which skips it."""
        if len(stream.stored) > 2 * DEDUP_HORIZON_MS // 100:
            horizon = stream.newest_ms - DEDUP_HORIZON_MS
            stream.stored = {t for t in stream.stored if t >= horizon}

    def _release(self, now_s: float, final: bool, late: list[tuple[str, int]]) -> list[dict]:
        """Estimate what the reorder buffers release, each vehicle's released samples in one `update_many` per run
        between gaps; the samples behind what was estimated go to `late`. The estimates' cells are looked up for the
        round at once (cells_of)."""
        window_ms = self.settings.reorder_window_s * 1000.0
        gap_ms = self.settings.max_gap_s * 1000.0
        estimates: list[dict] = []
        positions: list[dict] = []  # the sample of each estimate, for its position
        update_s: list[float] = []  # each sample's share of its run's time, into estimator_time once for the round
        for vehicle_id, stream in self._streams.items():
            if not stream.pending or stream.held_until_s is not None:
                continue
            quiet = final or now_s - stream.last_arrival_s >= self.settings.reorder_window_s
            limit = stream.newest_ms if quiet else stream.newest_ms - window_ms
            runs: list[list[dict]] = [[]]  # released samples, split where a gap restarts the estimator
            last = stream.last_estimated_ms
            pending = stream.pending
            while pending and pending[0][0] <= limit:
                ts, _, sample = heapq.heappop(pending)
                if last is not None and ts <= last:
                    late.append((sample["vehicle_id"], ts))
                    continue
                if last is not None and ts - last > gap_ms:
                    runs.append([])
                last = ts
                runs[-1].append(sample)
            stream.last_estimated_ms = last
            for k, run in enumerate(runs):
                if k:
                    self.estimator.reset(stream.state)
                    self.counters.restarts += 1
                if not run:
                    continue
                started = time.perf_counter()
                found = self.estimator.update_many(stream.state, run)
                update_s += [(time.perf_counter() - started) / len(run)] * len(run)
                estimates += found.rows()
                positions += [run[i] for i in found.index.tolist()]
            if last is not None and last >= stream.checkpoint_at_ms:
                self.checkpoints.due(vehicle_id, stream)
        self.estimator_time.add(update_s)
        latitudes = [sample.get("latitude_deg") for sample in positions]
        longitudes = [sample.get("longitude_deg") for sample in positions]
        cells = cells_of(latitudes, longitudes, self.settings.h3_resolution)
        for row, lat, lon, cell in zip(estimates, latitudes, longitudes, cells):
            row["latitude_deg"], row["longitude_deg"], row["h3_cell"] = lat, lon, cell
        return estimates
