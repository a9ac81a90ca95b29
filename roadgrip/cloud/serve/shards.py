"""Vehicles sharded over ingest processes (`ingest_processes: N`, N >= 1), so that the ingest path runs on more than
one core: one Python process runs Python on one core at a time, and at 10,000 samples/s the service alone held its
interpreter lock 82 % of the time (docs/RELIABILITY.md).

- The service's process keeps the HTTP API, the MQTT connection (one persistent session, as with no ingest
  processes), the credentials and the fan-out (roadgrip/cloud/pipeline/fanout.py: map, warnings, publishing), which need
  every vehicle.
- Ingest process k owns the vehicles with `shard_of(vehicle_id, N) == k`. It runs an `Ingest` (roadgrip/cloud/ingest/admission.py:
  parsing MQTT messages, the vehicle's rate limit, the pipeline: estimates and storage) with a database connection of
  its own. One process owns a vehicle, so its estimator state, its reorder buffer and its rate limit stay whole.
- An MQTT message is forwarded as it came (the raw payload and a token); the ingest process answers `ack` once its
  samples are stored (or at once when it refused the message whole), and `reject` with the rejections, which the
  service publishes on the vehicle's error topic. An HTTP request is parsed in the service (its errors are HTTP's)
  and its samples are submitted to the owner, whose answer resolves the request's future. After each round the
  ingest process sends what it stored to the fan-out, and its counters every STATS_INTERVAL_S (health sums them; the
  metrics, roadgrip/cloud/metrics.py, show them per process with their own).
- Backpressure as with no ingest processes, the MQTT client's `Busy` (roadgrip/cloud/transport/mqtt.py): a message
  for an ingest process that has MAX_FORWARDED_MESSAGES forwarded and not acknowledged is not forwarded; the handler
  raises `Busy`, the message stays unacknowledged (the client counts it deferred) and the broker delivers it again
  once every ingest process is down to half that (`has_room`, the client's `room`). paho's network thread never
  waits on a channel. An ingest process reads its channel all the time: a message its own pipeline has no room for
  (`Ingest.mqtt_message` raises Busy at MAX_MQTT_BACKLOG samples) waits there, in order, with every later one, until
  the pipeline has room.
- Each ingest process's pipeline checkpoints the estimator states of its own vehicles and restores them when it first
  sees them (roadgrip/cloud/pipeline/checkpoints.py), so a vehicle's calibration survives a restart of its process, and a
  change of `ingest_processes` too: the states are stored by vehicle_id, whichever process owns it next.
- An ingest process ignores SIGINT and SIGTERM (a terminal's Ctrl-C and systemd's stop reach the whole group): the
  service's process stops it after its own last message.
- An ingest process that dies is started again; the MQTT messages forwarded to it and not acknowledged are forwarded
  again (storing is idempotent: a sample stored before the crash is a duplicate), and the HTTP requests waiting on it
  fail with IngestUnavailable (503: nothing acknowledged). When the service's process dies, each ingest process sees
  its channel close, stores what it holds, and exits; the broker delivers what was not acknowledged again.

Channel messages, pickled over a `multiprocessing` pipe; service to ingest process: ("mqtt", token, vehicle_id,
payload), ("submit", request, vehicle_id, samples, received), ("forget", vehicle_id), ("stop",); back: ("ready",) or
("failed", traceback) once, then ("ack", token), ("reject", vehicle_id, rejections), ("result", request, SubmitResult
or exception), ("stored", estimates, stored_ms, newest_data_ms), ("stats", counters, metrics).
"""

from __future__ import annotations

import functools
import itertools
import logging
import multiprocessing as mp
import signal
import threading
import time
import traceback
import zlib
from concurrent.futures import Future, ThreadPoolExecutor

from roadgrip.cloud.ingest.admission import MAX_MQTT_BACKLOG, Ingest, IngestUnavailable, Rejecter, WaitingLine
from roadgrip.cloud.metrics import ProcessView
from roadgrip.cloud.pipeline.fanout import Fanout
from roadgrip.cloud.pipeline.pipeline import Pipeline, PipelineCounters
from roadgrip.cloud.process import rss_mb, tune_memory_for_serving, warm_up
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.transport.mqtt import Busy
from roadgrip.estimators.learned import load_estimator

log = logging.getLogger(__name__)

STATS_INTERVAL_S = 0.5  # how often an ingest process sends its counters
START_TIMEOUT_S = 180.0  # importing torch and numba and warming the estimator up, on a busy machine
RESTART_DELAY_S = 1.0  # wait before starting again an ingest process that failed to start
# MQTT messages forwarded to one ingest process and not acknowledged, at most: its pipeline's MAX_MQTT_BACKLOG in
# terminal messages of 10 samples (1 s at 10 Hz); beyond it the broker keeps them (Busy)
MAX_FORWARDED_MESSAGES = MAX_MQTT_BACKLOG // 10
_MAX_OF = ("last_round_s", "slowest_round_s")  # counters summed over processes, but for these


def shard_of(vehicle_id: str, count: int) -> int:
    """The ingest process (0 to count - 1) that owns a vehicle: stable across restarts and machines (CRC-32)."""
    return zlib.crc32(vehicle_id.encode()) % count


class _Shard:
    def __init__(self, index: int):
        self.index = index
        self.process = None
        self.conn = None
        self.lock = threading.Lock()  # sending, and replacing the process
        self.pending: dict[int, tuple[str, bytes, object]] = {}  # token -> (vehicle_id, payload, ack): unacknowledged
        self.requests: dict[int, Future] = {}  # HTTP submissions waiting for their answer
        self.stats: dict = {}
        self.metrics: dict = {}  # Ingest.metrics of the process, sent with its stats
        self.restarts = 0
        self.reader: threading.Thread | None = None


class IngestShards:
    """`Ingest`'s methods, each vehicle handed to the ingest process that owns it (module docstring)."""

    def __init__(self, settings: Settings, fanout: Fanout, reject: Rejecter):
        if settings.ingest_processes < 1:
            raise ValueError(f"IngestShards needs ingest_processes >= 1, got {settings.ingest_processes}")
        self.settings = settings
        self.fanout = fanout
        self.reject = reject
        self._context = mp.get_context("spawn")  # not fork: the service has threads (paho, uvicorn) by now
        self._shards = [_Shard(k) for k in range(settings.ingest_processes)]
        self._tokens = itertools.count()
        self._sender = ThreadPoolExecutor(1, thread_name_prefix="roadgrip-ingest-send")  # HTTP: never block the loop
        self._stopping = threading.Event()
        self._ticker: threading.Thread | None = None

    # ------------------------------------------------------------------------------------------------- lifecycle
    def start(self) -> None:
        try:
            for shard in self._shards:  # all start at once: each takes seconds to import and warm up
                self._launch(shard)
            for shard in self._shards:
                self._await_ready(shard)
        except BaseException:
            for shard in self._shards:
                if shard.process is not None:
                    shard.process.kill()
            raise
        for shard in self._shards:
            shard.reader = threading.Thread(
                target=self._read, args=(shard,), name=f"roadgrip-ingest-{shard.index}", daemon=True
            )
            shard.reader.start()
        self._ticker = threading.Thread(target=self._tick, name="roadgrip-fanout", daemon=True)
        self._ticker.start()
        log.info(
            "%d ingest processes started (pids %s)",
            len(self._shards),
            ", ".join(str(s.process.pid) for s in self._shards),
        )

    def stop(self, timeout_s: float = 30.0) -> None:
        """Each ingest process stores what it was given and stops; then the last estimates are published."""
        self._stopping.set()
        self._sender.shutdown(wait=True)
        for shard in self._shards:
            with shard.lock:
                self._send(shard, ("stop",))
        for shard in self._shards:
            if shard.reader is not None:
                shard.reader.join(timeout_s)
            shard.process.join(timeout_s)
            if shard.process.is_alive():
                log.error("ingest process %d did not stop within %.0f s: killed", shard.index, timeout_s)
                shard.process.kill()
            shard.conn.close()
        if self._ticker is not None:
            self._ticker.join(timeout_s)
        self.fanout.tick(final=True)

    @property
    def backlog(self) -> int:
        """Samples submitted and not yet taken by a round, in all ingest processes (as of their last counters)."""
        return sum(shard.stats.get("backlog", 0) for shard in self._shards)

    def _launch(self, shard: _Shard) -> None:
        conn, child = self._context.Pipe()
        shard.process = self._context.Process(
            target=serve_shard,
            args=(shard.index, self.settings.model_dump(), child, logging.getLogger().level),
            name=f"roadgrip-ingest-{shard.index}",
            daemon=True,
        )
        shard.process.start()
        child.close()
        shard.conn = conn

    def _await_ready(self, shard: _Shard) -> None:
        if not shard.conn.poll(START_TIMEOUT_S):
            shard.process.kill()
            raise RuntimeError(f"ingest process {shard.index} did not start within {START_TIMEOUT_S:.0f} s")
        try:
            message = shard.conn.recv()
        except EOFError:
            raise RuntimeError(
                f"ingest process {shard.index} exited while starting (exit code {shard.process.exitcode})"
            ) from None
        if message[0] != "ready":
            raise RuntimeError(f"ingest process {shard.index} failed to start:\n{message[1]}")

    # ------------------------------------------------------------------------------------------------- Ingest's methods
    def submit(self, vehicle_id: str, samples: list[dict], received: int, *, retry: bool = False) -> Future:
        """As `Ingest.submit`; the future may also fail with IngestUnavailable."""
        future: Future = Future()
        if self._stopping.is_set():
            future.set_exception(RuntimeError("the service is stopping"))
            return future
        shard = self._shards[shard_of(vehicle_id, len(self._shards))]
        request = next(self._tokens)

        def send() -> None:
            with shard.lock:
                shard.requests[request] = future
                self._send(shard, ("submit", request, vehicle_id, samples, received))

        self._sender.submit(send)
        return future

    def mqtt_message(self, vehicle_id: str, payload: bytes, ack) -> None:
        """As `Ingest.mqtt_message`: forwarded to the owner, acknowledged when it says so. Raises Busy, before
        forwarding, while the owner has MAX_FORWARDED_MESSAGES forwarded and not acknowledged (backpressure: the
        broker keeps the message)."""
        shard = self._shards[shard_of(vehicle_id, len(self._shards))]
        if len(shard.pending) >= MAX_FORWARDED_MESSAGES:
            raise Busy(f"ingest process {shard.index} has {len(shard.pending)} messages not acknowledged")
        token = next(self._tokens)
        with shard.lock:
            shard.pending[token] = (vehicle_id, payload, ack)
            self._send(shard, ("mqtt", token, vehicle_id, payload))

    def has_room(self) -> bool:
        """Whether messages refused with Busy may come again: every ingest process down to half its bound."""
        return all(len(shard.pending) <= MAX_FORWARDED_MESSAGES // 2 for shard in self._shards)

    def forget_vehicle(self, vehicle_id: str) -> None:
        shard = self._shards[shard_of(vehicle_id, len(self._shards))]
        with shard.lock:
            self._send(shard, ("forget", vehicle_id))

    def stats(self) -> dict:
        """The pipelines' counters summed (the slowest round: the slowest of any), their backlogs, whether any
        fails to write, and per ingest process its state (health: `pipeline`)."""
        parts = [shard.stats for shard in self._shards if shard.stats]
        summed: dict = {}
        for key in PipelineCounters.__dataclass_fields__:
            values = [part[key] for part in parts]
            summed[key] = max(values, default=0.0) if key in _MAX_OF else sum(values)
        summed["backlog"] = sum(part["backlog"] for part in parts)
        summed["storage_down"] = any(part["storage_down"] for part in parts)
        summed["forwarded_unacknowledged"] = sum(len(shard.pending) for shard in self._shards)
        summed["ingest_processes"] = [
            {
                "index": shard.index,
                "pid": shard.process.pid,
                "alive": shard.process.is_alive(),
                "restarts": shard.restarts,
                "backlog": shard.stats.get("backlog"),
                "rss_mb": rss_mb(shard.process.pid),
            }
            for shard in self._shards
        ]
        return summed

    def views(self) -> list[ProcessView]:
        """Each ingest process's pipeline as of its last counters (none before its first), for the metrics."""
        views = []
        for shard in self._shards:
            if not shard.stats:
                continue
            rss = rss_mb(shard.process.pid)
            views.append(
                ProcessView(
                    f"ingest-{shard.index}",
                    shard.stats,
                    shard.metrics,
                    restarts=shard.restarts,
                    alive=shard.process.is_alive(),
                    rss_bytes=None if rss is None else rss * 2**20,
                    forwarded_unacknowledged=len(shard.pending),
                )
            )
        return views

    # ------------------------------------------------------------------------------------------------- the channels
    def _send(self, shard: _Shard, message: tuple) -> None:
        """Send under shard.lock. A dead channel is left as it is: the reader starts the process again and forwards
        what is pending (an HTTP request sent to it fails then)."""
        try:
            shard.conn.send(message)
        except OSError:
            if not self._stopping.is_set():
                log.warning("ingest process %d is not reading; %s left for its restart", shard.index, message[0])

    def _read(self, shard: _Shard) -> None:
        while True:
            try:
                message = shard.conn.recv()
            except (EOFError, OSError):
                if self._stopping.is_set():
                    return
                self._restart(shard)
                continue
            try:
                self._handle(shard, message)
            except Exception:  # a bug must not stop this channel: log it and go on
                log.exception("handling %s from ingest process %d failed", message[0], shard.index)

    def _handle(self, shard: _Shard, message: tuple) -> None:
        kind = message[0]
        if kind == "ack":
            entry = shard.pending.pop(message[1], None)
            if entry is not None:
                entry[2]()
        elif kind == "stored":
            self.fanout.stored(*message[1:])
        elif kind == "stats":
            shard.stats, shard.metrics = message[1], message[2]
        elif kind == "reject":
            self.reject(message[1], message[2])
        elif kind == "result":
            future = shard.requests.pop(message[1], None)
            if future is not None and not future.done():
                if isinstance(message[2], BaseException):
                    future.set_exception(message[2])
                else:
                    future.set_result(message[2])
        else:
            log.error("unknown message %r from ingest process %d", kind, shard.index)

    def _restart(self, shard: _Shard) -> None:
        shard.process.join(5.0)
        shard.restarts += 1
        log.error(
            "ingest process %d stopped (exit code %s): starting it again, with the %d MQTT messages it had "
            "not acknowledged",
            shard.index,
            shard.process.exitcode,
            len(shard.pending),
        )
        with shard.lock:
            failed = IngestUnavailable(f"ingest process {shard.index} stopped; nothing was acknowledged, send again")
            for future in shard.requests.values():
                future.set_exception(failed)
            shard.requests.clear()
            shard.conn.close()
            try:
                self._launch(shard)
                self._await_ready(shard)
            except Exception:
                log.exception("ingest process %d failed to start; trying again in %.0f s", shard.index, RESTART_DELAY_S)
                time.sleep(RESTART_DELAY_S)
                return  # the reader finds the channel closed and comes back here
        # forwarded again from another thread: this one must go on reading (the process answers as it reads)
        threading.Thread(target=self._forward_again, args=(shard,), daemon=True).start()

    def _forward_again(self, shard: _Shard) -> None:
        with shard.lock:
            for token, (vehicle_id, payload, _) in list(shard.pending.items()):
                self._send(shard, ("mqtt", token, vehicle_id, payload))

    def _tick(self) -> None:
        while not self._stopping.wait(self.settings.flush_interval_s):
            try:
                self.fanout.tick()
            except Exception:
                log.exception("publishing the due estimates failed")


# ------------------------------------------------------------------------------------------------- an ingest process
class _ToService:
    """A pipeline's StoredSink in an ingest process: each stored round to the service's fan-out, the counters every
    STATS_INTERVAL_S."""

    def __init__(self, send):
        self.send = send
        self.ingest: Ingest | None = None
        self._next_stats = 0.0

    def stored(self, estimates: list[dict], stored_ms: float, newest_data_ms: int) -> None:
        self.send(("stored", estimates, stored_ms, newest_data_ms))

    def tick(self, final: bool) -> None:
        if final or time.monotonic() >= self._next_stats:
            self.send_stats()

    def send_stats(self) -> None:
        self._next_stats = time.monotonic() + STATS_INTERVAL_S
        self.send(("stats", self.ingest.stats(), self.ingest.metrics()))


def _answer(send, request: int, future: Future) -> None:
    send(("result", request, future.exception() or future.result()))


def _hand(ingest: Ingest, send, message: tuple) -> bool:
    """An MQTT message ("mqtt", token, vehicle_id, payload) to the pipeline; False when it has no room (Busy)."""
    _, token, vehicle_id, payload = message
    try:
        ingest.mqtt_message(vehicle_id, payload, functools.partial(send, ("ack", token)))
    except Busy:
        return False
    except Exception:  # as MqttClient does: logged, left unacknowledged
        log.exception("handling a message of %s failed; left unacknowledged", vehicle_id)
    return True


def serve_shard(index: int, settings_fields: dict, conn, log_level: int) -> None:
    """An ingest process's main (module docstring): start, say ready, then serve the channel until it closes or says
    stop; then store what is held, send the last counters and exit."""
    # the service's process decides when this one stops: Ctrl-C and a service manager's SIGTERM reach the whole process
    # group, and this process must not stop before the service has stopped sending to it
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, signal.SIG_IGN)
    logging.basicConfig(level=log_level, format=f"%(asctime)s ingest-{index} %(levelname)s %(name)s: %(message)s")
    lock = threading.Lock()

    def send(message: tuple) -> None:
        with lock:
            try:
                conn.send(message)
            except OSError:  # the service is gone: what is stored stays, what is not acknowledged comes again
                pass

    try:
        settings = Settings(**settings_fields)
        storage = open_storage(settings.storage_url)
        estimator = load_estimator(settings.estimator)
        warm_up(estimator)
    except Exception:
        log.exception("ingest process %d failed to start", index)
        send(("failed", traceback.format_exc()))
        return
    sink = _ToService(send)
    ingest = sink.ingest = Ingest(
        settings,
        Pipeline(storage, settings, estimator, sink),
        reject=lambda vehicle_id, errors: send(("reject", vehicle_id, errors)),
    )
    tune_memory_for_serving()
    send(("ready",))  # before the pipeline's first counters
    ingest.start()
    waiting: WaitingLine[tuple] = WaitingLine(ingest.has_room, functools.partial(_hand, ingest, send))
    try:
        while True:
            waiting.drain()
            try:
                if waiting and not conn.poll(settings.flush_interval_s):
                    continue  # room is looked for again
                message = conn.recv()
            except (EOFError, OSError):
                log.warning("the service's channel closed: storing what is held and stopping")
                break
            kind = message[0]
            if kind == "mqtt":
                waiting.offer(message)
            elif kind == "submit":
                _, request, vehicle_id, samples, received = message
                ingest.submit(vehicle_id, samples, received).add_done_callback(
                    functools.partial(_answer, send, request)
                )
            elif kind == "forget":
                ingest.forget_vehicle(message[1])
            elif kind == "stop":
                break
    finally:
        if waiting:
            log.warning(
                "%d MQTT messages found no room before the stop: not acknowledged, they come again", len(waiting)
            )
        ingest.stop()
        sink.send_stats()
        storage.close()
        conn.close()
