"""`roadgrip bench ingest`: vehicles at 10 Hz, end to end (ingest, estimate, stored), with counts that prove nothing was
lost, and beside it the ceilings of the broker and the database alone, measured in the same run.

Layout on one machine: the service runs as its own process (`roadgrip serve`, with its managed Mosquitto for MQTT);
`workers` load-generator processes (this module's `_drive`) play the vehicles, each vehicle with its own credentials,
connected before the start, sending a sample every 100 ms of wall-clock time (or `batch` samples every batch x 100 ms:
a terminal that buffers; what is sent is a `Messages`: `TelemetryMessages` here, edge vehicles' observations in
roadgrip/bench/ingest_edge.py);
the bench then waits until the service has stored everything it acknowledged and reads the counts from the database.
The load generators share the machine's cores with the service, so the figures are a floor for a service alone.

What a case reports, beside the rates: `lost` (acknowledged but not stored); `vehicles_stored_exactly`, the vehicles
whose stored telemetry is exactly what they sent (the count, the first and the last timestamp match their stream, and
the key (vehicle_id, timestamp_ms) is unique, so each sample is there once); the latency from a sample's timestamp to
its stored estimate over the whole run (`latency_p50_ms`, `latency_p99_ms`: the service's histogram, 10 ms bins); every
5 s a `timeline` point (stored, the service's queue, its RSS, its publishes waiting for the broker, the latency of the
last 100,000 estimates); the memory over the run's second half (`memory_trend`); `sustained`: every acknowledgement
within 5 % of the case's duration and everything stored within 2 s of the last one.

Samples are real telemetry: a few simulated runs of the random preset, cycled over the vehicles, each vehicle's stream
looping its run with timestamps that keep counting.

Size: over 500 lines because one benchmark: its load generator, its cases, the soak and the ceilings share the service
it starts.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import queue
import secrets
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import httpx

from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.storage.database import open_storage
from roadgrip.fleet.terminal import wire_samples

log = logging.getLogger(__name__)

SAMPLE_PERIOD_MS = 100
# How long after the period the load generators may take to report (their PUBACK wait is 60 s): past it the run is
# recorded with the counts of those that reported (`generators_finished`) and the others are stopped.
GENERATOR_GRACE_S = 300
DRAIN_LIMIT_S = 300  # after the last PUBACK, how long the service may take to store it; what is not stored counts lost
MEMORY_FLAT_FRACTION = 0.05  # a soak's memory is flat when RSS grows by at most this over the run's second half
# A load-generator process drives its MQTT vehicles' paho clients from one thread on one epoll selector (`_MqttFleet`):
# a thread per client (paho's loop_start) cost the 5,000 vehicles of docs/EDGE.md's soak both of this machine's cores
# (20 processes of 250 threads, a load average over 300). Each client holds three descriptors (its socket and paho's
# wake-up pair), so this many per process stays well under a ulimit of 20,000.
MQTT_CLIENTS_PER_PROCESS = 2_500


@dataclass(frozen=True)
class IngestCase:
    transport: str  # "http" or "mqtt"
    vehicles: int
    seconds: float
    batch: int  # samples per message
    workers: int = 2  # load-generator processes (MQTT: at least vehicles / MQTT_CLIENTS_PER_PROCESS)
    ingest_processes: int = 0  # the service's setting (roadgrip/cloud/serve/shards.py); 0: ingest in its own process

    def __post_init__(self):
        if self.transport == "mqtt":
            object.__setattr__(self, "workers", max(self.workers, -(-self.vehicles // MQTT_CLIENTS_PER_PROCESS)))


# ------------------------------------------------------------------------------------------------- telemetry
def sample_bodies(runs: int = 8, seed: int = 0) -> list[list[str]]:
    """Per simulated run, each sample as the JSON text of its fields minus vehicle_id and timestamp_ms (the load
    generator writes those two in front: formatting a string is far cheaper than json.dumps per message)."""
    import pyarrow.compute as pc

    from roadgrip.sim.presets import random_scenarios
    from roadgrip.sim.simulate import simulate

    table = simulate(random_scenarios(runs, seed))
    bodies = []
    for run_id in dict.fromkeys(table["run_id"].to_pylist()):
        run = table.filter(pc.equal(table["run_id"], run_id))
        samples = wire_samples(run, "x", 0)
        bodies.append(
            [json.dumps({k: v for k, v in s.items() if k not in ("vehicle_id", "timestamp_ms")})[1:-1] for s in samples]
        )
    return bodies


def _message(vehicle_id: str, timestamp_ms: int, body: str) -> str:
    return f'{{"vehicle_id":"{vehicle_id}","timestamp_ms":{timestamp_ms},{body}}}'


class Messages(Protocol):
    """What the load generator sends: vehicle k's message number `tick` is due `due_s(k, tick)` after the start (due
    times of a vehicle increase with tick, those of one tick by k's order at tick 0), holds `lines(...)` (the
    messages, one JSON object each: one MQTT message of them, an array when several) and goes to `topic(...)`.
    Picklable: it travels to each load-generator process."""

    def ticks(self, seconds: float) -> int: ...

    def due_s(self, k: int, tick: int) -> float: ...

    def topic(self, vehicle_id: str) -> str: ...

    def lines(self, vehicle_id: str, k: int, tick: int, base_ms: int) -> list[str]: ...


@dataclass(frozen=True)
class TelemetryMessages:
    """Raw telemetry: `batch` samples a message, every batch x 100 ms, all vehicles at once; vehicle k loops run k of
    `bodies` with live timestamps (sample j at the start + j x 100 ms)."""

    bodies: list[list[str]]
    batch: int

    def ticks(self, seconds: float) -> int:
        return int(seconds * 1000 / SAMPLE_PERIOD_MS) // self.batch

    def due_s(self, k: int, tick: int) -> float:
        # a batch leaves when its last sample has been measured (timestamps are never ahead of the clock)
        return ((tick + 1) * self.batch - 1) * SAMPLE_PERIOD_MS / 1000

    def topic(self, vehicle_id: str) -> str:
        from roadgrip.cloud.transport.mqtt import telemetry_topic

        return telemetry_topic(vehicle_id)

    def lines(self, vehicle_id: str, k: int, tick: int, base_ms: int) -> list[str]:
        run = self.bodies[k % len(self.bodies)]
        first = tick * self.batch
        return [
            _message(vehicle_id, base_ms + (first + j) * SAMPLE_PERIOD_MS, run[(first + j) % len(run)])
            for j in range(self.batch)
        ]


# ------------------------------------------------------------------------------------------------- load generator
def _drive(
    case: IngestCase,
    target: dict,
    vehicles: list[tuple[str, str]],
    messages: Messages,
    offset: int,
    ready,
    go,
    start,
    results,
) -> None:
    """One load-generator process: connects its vehicles (MQTT), says so on `ready`, waits for `go`, reads the start
    (s since the epoch) from `start`, then sends `messages` for case.seconds; puts (sent, acknowledged, refused, when
    the last acknowledgement came, worst lag) on `results`, counting the lines of the messages."""
    n_ticks = messages.ticks(case.seconds)
    sent = acked = refused = 0
    lag_s = 0.0  # how late the most belated message left: the generator itself falling behind
    if case.transport == "mqtt":
        fleet = _MqttFleet(target["mqtt_url"], vehicles)
        topics = [messages.topic(vid) for vid, _ in vehicles]
        infos = []  # (MQTTMessageInfo, lines)
    else:
        from concurrent.futures import ThreadPoolExecutor

        http = httpx.Client(
            base_url=target["http_url"],
            timeout=60.0,
            limits=httpx.Limits(max_connections=32, max_keepalive_connections=32),
        )
        pool = ThreadPoolExecutor(32)
        futures = []

        def post(vid: str, secret: str, body: str):
            return http.post(
                "/v1/telemetry", content=body, auth=(vid, secret), headers={"content-type": "application/x-ndjson"}
            )

    ready.put(len(vehicles))
    go.wait()
    start_wall = start.value
    base_ms = int(start_wall * 1000)
    order = sorted(range(len(vehicles)), key=lambda i: messages.due_s(offset + i, 0))
    for tick in range(n_ticks):
        last_due = None
        for i in order:
            vid, secret = vehicles[i]
            due = start_wall + messages.due_s(offset + i, tick)
            if due != last_due:
                last_due = due
                wait = due - time.time()
                lag_s = max(lag_s, -wait)
                if case.transport == "mqtt":
                    fleet.run_until(due)  # reading PUBACKs meanwhile (at least once when late)
                elif wait > 0:
                    time.sleep(wait)
            lines = messages.lines(vid, offset + i, tick, base_ms)
            if case.transport == "mqtt":
                payload = lines[0] if len(lines) == 1 else ("[" + ",".join(lines) + "]")
                infos.append((fleet.clients[i].publish(topics[i], payload, qos=1), len(lines)))
            else:
                futures.append((pool.submit(post, vid, secret, "\n".join(lines)), len(lines)))
            sent += len(lines)
    if case.transport == "mqtt":
        deadline = time.time() + 60
        while time.time() < deadline and not all(info.is_published() for info, _ in infos):
            fleet.run_until(time.time() + 0.5)
        acked = sum(n for info, n in infos if info.is_published())
        refused = fleet.refused
        acked -= refused * case.batch
        fleet.close()
    else:
        for f, n in futures:
            answer = f.result()
            if answer.status_code == 200:
                acked += answer.json()["accepted"]
            else:
                refused += n
        pool.shutdown()
        http.close()
    done_at = time.time()  # the last acknowledgement is in
    results.put((sent, acked, refused, done_at, lag_s))


class _MqttFleet:
    """A load generator's vehicles: one paho client each (MQTT 5, clean start, its own login), all driven from the
    calling thread through paho's external-loop calls (loop_read on what the epoll selector finds readable; a publish
    is written at once; loop_write and loop_misc, keepalive included, every second for every client)."""

    def __init__(self, url: str, vehicles: list[tuple[str, str]], timeout_s: float = 120.0):
        import selectors

        import paho.mqtt.client as paho
        from paho.mqtt.enums import CallbackAPIVersion

        from roadgrip.cloud.transport.mqtt import parse_url

        host, port = parse_url(url)
        self.refused = 0  # PUBACKs with a failure reason code
        self.selector = selectors.DefaultSelector()
        self.clients = []
        for vehicle_id, secret in vehicles:
            client = paho.Client(
                CallbackAPIVersion.VERSION2, client_id=f"{vehicle_id}-{secrets.token_hex(4)}", protocol=paho.MQTTv5
            )
            client.username_pw_set(vehicle_id, secret)
            client.on_publish = self._on_publish
            client.connect(host, port, keepalive=60)
            self.selector.register(client.socket(), selectors.EVENT_READ, client)
            self.clients.append(client)
        self._swept = 0.0
        deadline = time.time() + timeout_s
        while not all(c.is_connected() for c in self.clients):
            if time.time() > deadline:
                missing = sum(not c.is_connected() for c in self.clients)
                raise TimeoutError(f"{missing} of {len(self.clients)} MQTT vehicles not connected in {timeout_s} s")
            self.run_until(time.time() + 0.2)

    def _on_publish(self, _client, _userdata, _mid, reason_code, _properties):
        if reason_code.is_failure:
            self.refused += 1

    def run_until(self, until: float) -> None:
        """Read what arrives (CONNACKs, PUBACKs) until `until` (s since the epoch); at least once, even when it has
        passed."""
        while True:
            for key, _ in self.selector.select(max(0.0, min(until - time.time(), 0.5))):
                key.data.loop_read()
            if time.time() - self._swept >= 1.0:
                self._swept = time.time()
                for client in self.clients:
                    if client.want_write():
                        client.loop_write()
                    client.loop_misc()
            if time.time() >= until:
                return

    def close(self) -> None:
        for client in self.clients:
            client.disconnect()
        self.selector.close()


def _generate(
    case: IngestCase, target: dict, vehicles: list[tuple[str, str]], messages: Messages, on_tick=None
) -> dict:
    """Run the load generators; counts of lines (samples or observations) sent, acknowledged and refused, when sending
    started (once every generator had connected its vehicles, plus a second) and how long until the last
    acknowledgement (longer than case.seconds when the generators or the service could not keep the pace)."""
    ctx = mp.get_context("spawn")
    results, ready = ctx.Queue(), ctx.Queue()
    go, start = ctx.Event(), ctx.Value("d", 0.0)
    share = -(-len(vehicles) // case.workers)
    procs = [
        ctx.Process(
            target=_drive,
            args=(case, target, vehicles[k * share : (k + 1) * share], messages, k * share, ready, go, start, results),
        )
        for k in range(case.workers)
        if vehicles[k * share : (k + 1) * share]
    ]
    for p in procs:
        p.start()
    connected, deadline = 0, time.time() + 120 + len(vehicles) / 25
    while connected < len(vehicles):
        try:
            connected += ready.get(timeout=5.0)
        except queue.Empty:
            if time.time() > deadline or any(p.exitcode is not None for p in procs):
                for p in procs:
                    p.kill()
                raise TimeoutError(f"the load generators connected {connected} of {len(vehicles)} vehicles") from None
            if on_tick is not None:
                on_tick()
    start.value = start_wall = time.time() + 1.0
    go.set()
    deadline = start_wall + case.seconds + GENERATOR_GRACE_S
    totals = []
    while len(totals) < len(procs):
        try:
            totals.append(results.get(timeout=5.0))
        except queue.Empty:
            if time.time() > deadline:  # the run is still recorded: its counts are those of the generators that ended
                log.warning("%d of %d load generators did not finish; stopped", len(procs) - len(totals), len(procs))
                break
            if on_tick is not None:
                on_tick()
    for p in procs:
        if len(totals) < len(procs):
            p.kill()
        p.join()
    return {
        "sent": sum(t[0] for t in totals),
        "acknowledged": sum(t[1] for t in totals),
        "refused": sum(t[2] for t in totals),
        "generators": len(procs),
        "generators_finished": len(totals),
        "start_wall": start_wall,
        "base_ms": int(start_wall * 1000),
        "generator_lag_max_s": max((t[4] for t in totals), default=float("nan")),
        "acked_s": max((t[3] for t in totals), default=float("nan")) - start_wall,
    }


# ------------------------------------------------------------------------------------------------- the service
class _Service:
    """`roadgrip serve` in its own process, in a scratch folder."""

    def __init__(self, workdir: Path, mqtt: bool, database_url: str | None, ingest_processes: int = 0):
        self.workdir = workdir
        self.admin = ("admin", secrets.token_urlsafe(24))
        self.port = free_port()
        env = {
            **os.environ,
            "ROADGRIP_ADMIN_SECRET": self.admin[1],
            "ROADGRIP_DATA_DIR": str(workdir),
            "ROADGRIP_PORT": str(self.port),
            "ROADGRIP_MQTT": "managed" if mqtt else "off",
            "ROADGRIP_MAP_CLOCK": "data",
            "ROADGRIP_INGEST_PROCESSES": str(ingest_processes),
        }
        if database_url:
            env["ROADGRIP_DATABASE_URL"] = database_url
        self.log = open(workdir / "serve.log", "w")  # noqa: SIM115 (the server's output for its whole life)
        self.process = subprocess.Popen(
            [sys.executable, "-m", "roadgrip", "serve"], env=env, stdout=self.log, stderr=subprocess.STDOUT
        )
        self.http = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", auth=self.admin, timeout=120.0)
        deadline = time.time() + 120
        while True:
            if self.process.poll() is not None:
                raise RuntimeError(f"roadgrip serve exited:\n{(workdir / 'serve.log').read_text()[-3000:]}")
            try:
                self.health()
                break
            except httpx.HTTPError:
                if time.time() > deadline:
                    raise RuntimeError("roadgrip serve did not answer within 120 s") from None
                time.sleep(0.3)

    def cpu_s(self) -> dict[str, float]:
        """CPU seconds used so far by the service (with its ingest processes), by its ingest processes alone, and by
        its broker (a child process too), from /proc."""
        used = {"service": _cpu_s(self.process.pid), "ingest": 0.0, "broker": 0.0}
        children = Path(f"/proc/{self.process.pid}/task/{self.process.pid}/children")
        for pid in children.read_text().split() if children.exists() else []:
            try:
                broker = Path(f"/proc/{pid}/comm").read_text().strip() == "mosquitto"
            except OSError:
                continue
            seconds = _cpu_s(int(pid))
            if broker:
                used["broker"] += seconds
            else:
                used["ingest"] += seconds
                used["service"] += seconds
        return used

    def health(self) -> dict:
        return self.http.get("/v1/health").raise_for_status().json()

    def register(self, n: int) -> tuple[list[tuple[str, str]], str | None]:
        body = [{"vehicle_id": f"bench-{i:05d}", "profile": "paper-suv"} for i in range(n)]
        issued = self.http.post("/v1/vehicles", json=body).raise_for_status().json()
        return [(c["name"], c["secret"]) for c in issued], issued[0]["mqtt_url"]

    def stop(self) -> None:
        self.http.close()
        self.process.terminate()
        try:
            self.process.wait(30)
        except subprocess.TimeoutExpired:
            self.process.kill()
        self.log.close()


def _cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime + stime


def run_case(case: IngestCase, bodies: list[list[str]], database_url: str | None = None, progress=print) -> dict:
    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-") as tmp:
        service = _Service(Path(tmp), case.transport == "mqtt", database_url, case.ingest_processes)
        try:
            vehicles, mqtt_url = service.register(case.vehicles)
            target = {"http_url": f"http://127.0.0.1:{service.port}", "mqtt_url": mqtt_url}
            progress(f"{case.transport}: {case.vehicles} vehicles x {case.seconds:.0f} s, batch {case.batch}")
            cpu_before = service.cpu_s()
            timeline = []
            started = time.time()

            def record() -> None:  # every 5 s: what a soak must show flat
                h = service.health()
                timeline.append(
                    {
                        "t_s": round(time.time() - started, 1),
                        "stored": h["pipeline"]["stored"],
                        "backlog": h["pipeline"]["backlog"],
                        "rss_mb": h["memory_rss_mb"],
                        "ingest_rss_mb": [p["rss_mb"] for p in h["pipeline"].get("ingest_processes", [])],
                        "slow_rounds": h["pipeline"]["slow_rounds"],
                        "mqtt_unacknowledged": h["pipeline"]["mqtt_unacknowledged"],
                        **{k: round(h["pipeline"][k], 2) for k in ("estimate_s", "write_s", "fanout_s")},
                        **h["pipeline"]["latency"],
                    }
                )

            load = _generate(case, target, vehicles, TelemetryMessages(bodies, case.batch), on_tick=record)
            # drain: everything acknowledged is stored, nothing left in the reorder buffers
            drain_s = drain(lambda: service.health()["pipeline"], "stored", load["acknowledged"])
            stored_at = time.time()
            cpu_after = service.cpu_s()
            time.sleep(1.0)  # the last reorder windows
            health = service.health()
            pipeline = health["pipeline"]
            storage = open_storage(database_url or f"sqlite:///{Path(tmp) / 'roadgrip.sqlite'}")
            counts = storage.counts()
            extent = storage.telemetry_extent()
            storage.close()
        finally:
            service.stop()
    e2e_s = stored_at - load["start_wall"]
    per_vehicle = int(case.seconds * 1000 / SAMPLE_PERIOD_MS) // case.batch * case.batch
    expected = (per_vehicle, load["base_ms"], load["base_ms"] + (per_vehicle - 1) * SAMPLE_PERIOD_MS)
    since_start = pipeline["latency_since_start"]
    return {
        "case": case.transport,
        "vehicles": case.vehicles,
        "batch": case.batch,
        "seconds": case.seconds,
        "ingest_processes": case.ingest_processes,
        "offered_per_s": case.vehicles * 1000 / SAMPLE_PERIOD_MS,
        "sent": load["sent"],
        "acked_s": round(load["acked_s"], 2),
        "acked_per_s": load["acknowledged"] / load["acked_s"],
        "acknowledged": load["acknowledged"],
        "refused": load["refused"],
        "stored_rows": counts["telemetry"],
        "estimate_rows": counts["estimates"],
        "lost": load["acknowledged"] - counts["telemetry"],
        "end_to_end_s": round(e2e_s, 2),
        "stored_per_s": counts["telemetry"] / e2e_s,
        "drain_s": round(drain_s, 2),
        "failed_rounds": pipeline["failed_rounds"],
        "service_cpu_s": round(cpu_after["service"] - cpu_before["service"], 1),
        "broker_cpu_s": round(cpu_after["broker"] - cpu_before["broker"], 1),
        "ingest_cpu_s": round(cpu_after["ingest"] - cpu_before["ingest"], 1),
        "vehicles_stored_exactly": sum(extent.get(vid) == expected for vid, _ in vehicles),
        "latency_p50_ms": since_start["p50_ms"],
        "latency_p99_ms": since_start["p99_ms"],
        "latency_over_max": since_start["over_max"],
        "rss_mb_end": health["memory_rss_mb"],
        "slowest_round_s": round(pipeline["slowest_round_s"], 2),
        "slow_rounds": pipeline["slow_rounds"],
        "generator_lag_max_s": round(load["generator_lag_max_s"], 2),
        "estimate_messages_dropped": pipeline["estimate_messages_dropped"],
        # estimator state checkpoints while serving (roadgrip/cloud/pipeline/checkpoints.py; not those of the stop)
        "checkpoints_written": pipeline["checkpoints_written"],
        "checkpoint_s": round(pipeline["checkpoint_s"], 3),
        **memory_trend(timeline),
        "timeline": timeline,
        "sustained": load["acked_s"] <= 1.05 * case.seconds + 1.0 and drain_s <= 2.0,
    }


def drain(read, stored_key: str, acknowledged: int, limit_s: float = DRAIN_LIMIT_S, poll_s: float = 0.1) -> float:
    """Wait until `read()` (a health section) counts `acknowledged` under `stored_key` with an empty backlog, or
    `limit_s` has passed; the seconds waited."""
    start = time.time()
    while True:
        counts = read()
        if (counts[stored_key] >= acknowledged and counts["backlog"] == 0) or time.time() - start > limit_s:
            return time.time() - start
        time.sleep(poll_s)


def memory_trend(timeline: list[dict]) -> dict:
    """The service's memory over the second half of a run: RSS at its start and end, the growth per minute, and
    whether it is flat (grew by at most MEMORY_FLAT_FRACTION of the RSS at half-time)."""
    points = [p for p in timeline if p["rss_mb"] is not None]
    if len(points) < 4:
        return {"rss_mb_half": None, "rss_growth_mb_per_min": None, "memory_flat": None}
    half = min(points, key=lambda p: abs(p["t_s"] - points[-1]["t_s"] / 2))
    end = points[-1]
    growth = end["rss_mb"] - half["rss_mb"]
    return {
        "rss_mb_half": half["rss_mb"],
        "rss_growth_mb_per_min": 60 * growth / (end["t_s"] - half["t_s"]),
        "memory_flat": growth <= MEMORY_FLAT_FRACTION * half["rss_mb"],
    }


# ------------------------------------------------------------------------------------------------- ceilings
def database_ceiling(bodies: list[list[str]], database_url: str | None = None, rows: int = 200_000) -> dict:
    """Telemetry rows per second through Storage.write_batch alone, 1,000-row batches, a fresh database."""
    samples = [
        json.loads(
            _message(
                f"db-{k % 1000:04d}",
                1_700_000_000_000 + k * SAMPLE_PERIOD_MS,
                bodies[k % len(bodies)][k % len(bodies[k % len(bodies)])],
            )
        )
        for k in range(rows)
    ]
    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-db-") as tmp:
        storage = open_storage(database_url or f"sqlite:///{Path(tmp) / 'ceiling.sqlite'}")
        started = time.perf_counter()
        for k in range(0, rows, 1000):
            storage.write_batch(samples[k : k + 1000], [])
        elapsed = time.perf_counter() - started
        stored = storage.counts()["telemetry"]
        storage.close()
    return {"case": f"database alone ({storage.dialect})", "rows": stored, "rows_per_s": stored / elapsed}


def broker_ceiling(bodies: list[list[str]], vehicles: int, seconds: float, batch: int = 1, workers: int = 2) -> dict:
    """The same load through a managed Mosquitto alone: the same generator and pace, received by the service's MQTT
    client (`MqttClient`) with a handler that only counts and acknowledges: what the broker (and the generator on
    this machine) deliver with nothing else to do."""
    import threading

    from roadgrip.cloud.transport.mosquitto import ManagedBroker
    from roadgrip.cloud.transport.mqtt import MqttClient

    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-mqtt-") as tmp, ManagedBroker(Path(tmp)) as broker:
        logins = [(f"raw-{i:05d}", secrets.token_urlsafe(16)) for i in range(vehicles)]
        broker.set_users([(name, secret, "vehicle", name) for name, secret in logins])
        received = [0]
        lock = threading.Lock()

        def count(_vehicle_id: str, _payload: bytes, ack) -> None:
            with lock:
                received[0] += 1
            ack()

        counter = MqttClient(
            broker.url, broker.service_user, broker.service_password, "bench-counter", on_telemetry=count
        )
        counter.connect()
        case = IngestCase("mqtt", vehicles, seconds, batch, workers)
        load = _generate(case, {"mqtt_url": broker.url}, logins, TelemetryMessages(bodies, batch))
        deadline = time.time() + 60
        while received[0] * batch < load["acknowledged"] and time.time() < deadline:
            time.sleep(0.05)
        ended = time.time()
        counter.close()
    elapsed = ended - load["start_wall"]
    return {
        "case": f"broker alone (mosquitto, QoS 1, {batch} sample(s) a message)",
        "batch": batch,
        "sent": load["sent"],
        "acknowledged": load["acknowledged"],
        "messages_received": received[0],
        "messages_per_s": received[0] / elapsed,
        "samples_per_s": received[0] * batch / elapsed,
    }


def format_ingest(rows: list[dict]):
    """The cases side by side, a line per figure (a rich Table)."""
    from rich.table import Table

    def latency(r):
        return "-" if r["latency_p50_ms"] is None else f"{r['latency_p50_ms']:,.0f} / {r['latency_p99_ms']:,.0f}"

    lines = [
        ("samples per message (MQTT) or request (HTTP)", lambda r: str(r["batch"])),
        ("ingest processes (0: in the service's)", lambda r: str(r.get("ingest_processes", 0))),
        ("offered, samples/s", lambda r: f"{r['offered_per_s']:,.0f}"),
        ("acknowledged, samples/s", lambda r: f"{r['acked_per_s']:,.0f}"),
        ("sent / acknowledged / refused", lambda r: f"{r['sent']:,} / {r['acknowledged']:,} / {r['refused']:,}"),
        ("stored / lost / estimates", lambda r: f"{r['stored_rows']:,} / {r['lost']:,} / {r['estimate_rows']:,}"),
        ("vehicles stored exactly as sent", lambda r: f"{r['vehicles_stored_exactly']:,} of {r['vehicles']:,}"),
        ("stored end to end, samples/s", lambda r: f"{r['stored_per_s']:,.0f}"),
        ("stored after the last ack, s", lambda r: f"{r['drain_s']:.1f}"),
        ("latency to stored estimate p50 / p99, ms", latency),
        (
            "service RSS (with its ingest processes) at half-time / end, MB",
            lambda r: ("-" if r["rss_mb_half"] is None else f"{r['rss_mb_half']:,.0f}") + f" / {r['rss_mb_end']:,.0f}",
        ),
        (
            "RSS growth over the second half, MB/min",
            lambda r: (
                "-"
                if r["rss_growth_mb_per_min"] is None
                else f"{r['rss_growth_mb_per_min']:+.1f}" + (" (flat)" if r["memory_flat"] else " (growing)")
            ),
        ),
        (
            "CPU s: service (of which ingest processes) / broker",
            lambda r: f"{r['service_cpu_s']:.1f} ({r.get('ingest_cpu_s', 0.0):.1f}) / {r['broker_cpu_s']:.1f}",
        ),
        ("slowest pipeline round, s (rounds over 1 s)", lambda r: f"{r['slowest_round_s']:.2f} ({r['slow_rounds']})"),
        ("load generator's worst lag, s", lambda r: f"{r['generator_lag_max_s']:.2f}"),
        ("estimate messages dropped (broker behind)", lambda r: f"{r['estimate_messages_dropped']:,}"),
        ("sustained", lambda r: "yes" if r["sustained"] else "no"),
    ]
    table = Table(title=f"roadgrip bench ingest: {rows[0]['vehicles']:,} vehicles at 10 Hz, {rows[0]['seconds']:.0f} s")
    table.add_column("")
    for r in rows:
        table.add_column(r["case"], justify="right")
    for name, show in lines:
        table.add_row(name, *(show(r) for r in rows))
    return table


def plot_timelines(rows: list[dict], path: Path) -> Path:
    """Memory, backlog and latency over the run of each case: a soak must show them flat."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(8, 7), sharex=True)
    for row in rows:
        t = [p["t_s"] for p in row["timeline"]]
        label = f"{row['case']}, {row['batch']} a message"
        axes[0].plot(t, [p["rss_mb"] for p in row["timeline"]], label=label)
        axes[1].plot(t, [p["backlog"] for p in row["timeline"]], label=label)
        axes[2].plot(t, [p["p99_ms"] for p in row["timeline"]], label=f"{label}, p99")
        axes[2].plot(t, [p["p50_ms"] for p in row["timeline"]], "--", label=f"{label}, p50")
    axes[0].set_ylabel("service RSS, MB")
    axes[1].set_ylabel("queued samples")
    axes[2].set_ylabel("sample to stored\nestimate, ms")
    axes[2].set_xlabel("time since the start, s")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.suptitle(f"roadgrip bench ingest: {rows[0]['vehicles']} vehicles at 10 Hz")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
