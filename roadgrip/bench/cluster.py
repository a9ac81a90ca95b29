"""`roadgrip bench cluster`: the capacity of cluster mode, measured in one run on one machine (docs/CLUSTER.md,
"Capacity").

What runs: a 3-node RabbitMQ cluster (roadgrip/cloud/transport/amqp.py `RabbitCluster`: MQTT plugin, the partition
topology, one user per vehicle) and a PostgreSQL server (roadgrip/cloud/storage/local_postgres.py `LocalPostgres`),
both on 127.0.0.1; simulated vehicles in load-generator processes (`_drive`), each vehicle its own MQTT 3.1.1
connection, spread over the three nodes, publishing QoS 1 messages of SAMPLES_PER_MESSAGE samples (1 s of a terminal's
data at 10 Hz, real telemetry of simulated runs) to its own telemetry topic.

Pace, two of them:
- the broker's ceiling: as fast as PUBACKs allow, IN_FLIGHT messages unacknowledged per vehicle (the next leaves
  when a PUBACK comes): a ceiling is measured by offering more than it.
- the workers: `rate` messages a second per vehicle, 1 by default, like a terminal (10 samples a second), so the
  offered load is vehicles x rate x 10 samples a second and the workers are measured against a fleet's pace. Not as
  fast as PUBACKs allow: on this machine the load generators and the broker would then take every core and starve
  the workers (in a trial, 1 worker stored a twentieth of what the vehicles got PUBACKed), so the figure would be
  the generators' and not the workers'. Whether the workers kept up shows in the partition queues: messages
  ready at the start and the end of the window (growing: the workers are the bottleneck), and in `held_back`
  (messages a vehicle skipped because IN_FLIGHT were unacknowledged: the broker was). To find the workers' ceiling,
  raise `vehicles` (or `rate`) until the backlog grows.
At a rate of at most 1 the vehicles' timestamps follow the clock (live data, as the map and warnings see it from
terminals); faster, and as fast as PUBACKs allow, data time runs ahead of the clock, so it starts 30 days back and
no timestamp is in the future.

Cases, in this order, each for `seconds` after a warm-up, the vehicles connecting afresh for each:
- the broker's own ceiling: consumers in this process that only acknowledge (one connection per partition queue,
  a multiple-ack every ACK_EVERY messages or FLUSH_S): PUBACKed messages per second and consumed per second;
- for each count in `workers`: that many `roadgrip worker` processes on a fresh database. The window starts once
  every partition is taken and spread (each worker holds at most ceil(partitions / workers)), or after SPREAD_WAIT_S
  (`spread_s` is then None). Stored samples per second are counted in the database (rows of telemetry) over the
  window; beside them the offered and the PUBACKed samples per second and the queues' backlog.

Everything shares this machine's cores: the load generators, three broker nodes, PostgreSQL and the workers. The
figures are this machine's, for the whole set-up; see docs/CLUSTER.md for how to read them.

Size: over 500 lines because one benchmark: the broker's ceiling and the workers' throughput share the cluster it
starts.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import secrets
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import pika
import psycopg
from sqlalchemy.engine import make_url

from roadgrip.cloud.transport.amqp import HOST, RabbitCluster, partition_queue
from roadgrip.cloud.transport.mqtt import telemetry_topic

SAMPLES_PER_MESSAGE = 10  # 1 s of a terminal's data at 10 Hz
SAMPLE_PERIOD_MS = 100
IN_FLIGHT = 10  # messages a vehicle keeps unacknowledged (paho's default allows 20)
VEHICLES_PER_GENERATOR = 200  # paho's select() takes descriptors below 1024, three per client
WARM_UP_S = 3.0  # publishing before a window starts
SPREAD_WAIT_S = 90.0  # the most a worker case waits for its partitions to spread before measuring anyway
ACK_EVERY = 50  # the ack-only consumers' multiple-ack
FLUSH_S = 0.05
DATA_START_MS_AGO = 30 * 86_400_000  # where the vehicles' data time runs faster than the clock, it starts this far back
ROADGRIP = Path(sys.executable).parent / "roadgrip"

Progress = Callable[[str, float | None], None]  # (what is being done, fraction of the run done or None)


@dataclass(frozen=True)
class ClusterBench:
    vehicles: int = 500
    seconds: float = 20.0
    workers: tuple[int, ...] = (1, 2, 4)
    partitions: int = 8
    rate: float = 1.0  # messages a second per vehicle in the worker cases (0: as fast as PUBACKs allow)
    payload: str = "json"  # how the vehicles encode a message: json, or arrow (an Arrow IPC stream, CONTRACTS 3.1)

    def __post_init__(self):
        if self.vehicles < 1:
            raise ValueError(f"vehicles must be at least 1, got {self.vehicles}")
        if self.seconds <= 0:
            raise ValueError(f"seconds must be positive, got {self.seconds}")
        if not self.workers or any(w < 1 for w in self.workers):
            raise ValueError(f"workers must be positive counts, got {self.workers}")
        if self.partitions < 1:
            raise ValueError(f"partitions must be at least 1, got {self.partitions}")
        if self.rate < 0:
            raise ValueError(f"rate must be 0 (as fast as PUBACKs allow) or positive, got {self.rate}")
        if self.payload not in ("json", "arrow"):
            raise ValueError(f"payload must be json or arrow, got {self.payload!r}")


@dataclass
class _Load:
    """The load generators of one case: start them, read their counters, stop them."""

    processes: list = field(default_factory=list)
    counters: object = None  # mp.Array: per generator, PUBACKed messages, vehicles connected, messages held back
    stop: object = None  # mp.Event

    def acked_messages(self) -> int:
        return sum(self.counters[0::3])

    def connected_vehicles(self) -> int:
        return sum(self.counters[1::3])

    def held_back(self) -> int:
        return sum(self.counters[2::3])


# ------------------------------------------------------------------------------------------------- load generator
def sample_bodies() -> list[list[str]]:
    """Real telemetry: simulated runs as JSON fragments without vehicle_id and timestamp_ms (roadgrip/bench/ingest.py)."""
    from roadgrip.bench.ingest import sample_bodies as ingest_bodies

    return ingest_bodies(runs=4)


def _drive(
    slot: int,
    ports: list[int],
    secret: str,
    vehicles: list[str],
    bodies: list[list[str]],
    start_ms: int,
    rate: float,
    counters,
    stop,
    payload: str = "json",
) -> None:
    """One load-generator process (module docstring). Its vehicles connect; then, until `stop`, with `rate` 0 each
    keeps IN_FLIGHT messages unacknowledged (the next leaves when a PUBACK comes), else each publishes `rate`
    messages a second (the vehicles staggered over the period), skipping a message while IN_FLIGHT are
    unacknowledged (counted: the broker held it back). Then it waits up to 10 s for the last PUBACKs and
    disconnects. `counters[slot]`: PUBACKed messages, vehicles connected, messages held back."""
    import paho.mqtt.client as paho
    from paho.mqtt.enums import CallbackAPIVersion

    lock = threading.Lock()
    counts = {"sent": 0, "acked": 0, "connected": 0, "held_back": 0}
    fleet = []

    parsed: dict[int, list[dict]] = {}  # Arrow: each run's samples as dicts, parsed once

    def message(k: int, vehicle: str, run: list[str]) -> str | bytes:
        first = k * SAMPLES_PER_MESSAGE
        if payload == "arrow":
            from roadgrip.cloud.ingest.wire import arrow_payload

            rows = parsed.setdefault(id(run), [json.loads("{" + fragment + "}") for fragment in run])
            return arrow_payload(
                [
                    {
                        "vehicle_id": vehicle,
                        "timestamp_ms": start_ms + (first + j) * SAMPLE_PERIOD_MS,
                        **rows[(first + j) % len(rows)],
                    }
                    for j in range(SAMPLES_PER_MESSAGE)
                ]
            )
        return (
            "["
            + ",".join(
                f'{{"vehicle_id":"{vehicle}","timestamp_ms":{start_ms + (first + j) * SAMPLE_PERIOD_MS},'
                f"{run[(first + j) % len(run)]}}}"
                for j in range(SAMPLES_PER_MESSAGE)
            )
            + "]"
        )

    def publish(client, state) -> None:
        client.publish(state["topic"], message(state["next"], state["vehicle"], state["run"]), qos=1)
        state["next"] += 1
        with lock:
            counts["sent"] += 1

    def report() -> None:
        counters[3 * slot : 3 * slot + 3] = [counts["acked"], counts["connected"], counts["held_back"]]

    for i, vehicle in enumerate(vehicles):
        client = paho.Client(CallbackAPIVersion.VERSION2, client_id=vehicle, protocol=paho.MQTTv311, clean_session=True)
        client.username_pw_set(vehicle, secret)
        client.max_inflight_messages_set(IN_FLIGHT)
        state = {
            "next": 0,
            "acked": 0,
            "topic": telemetry_topic(vehicle),
            "run": bodies[i % len(bodies)],
            "vehicle": vehicle,
        }

        def on_connect(c, userdata, flags, rc, props, state=state):
            if rc.is_failure or state["next"]:
                return
            with lock:
                counts["connected"] += 1
                report()
            if not rate:
                for _ in range(IN_FLIGHT):
                    publish(c, state)

        def on_publish(c, userdata, mid, rc, props, state=state):
            state["acked"] += 1
            with lock:
                counts["acked"] += 1
                report()
            if not rate and not stop.is_set():
                publish(c, state)

        client.on_connect = on_connect
        client.on_publish = on_publish
        client.connect_async(HOST, ports[i % len(ports)])
        client.loop_start()
        fleet.append((client, state))
    if rate:
        while counts["connected"] < len(fleet) and not stop.wait(0.1):
            pass
        period, started, tick = 1.0 / rate, time.monotonic(), 0
        while not stop.is_set():
            for i, (client, state) in enumerate(fleet):
                delay = started + (tick + i / len(fleet)) * period - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
                if state["next"] - state["acked"] < IN_FLIGHT:
                    publish(client, state)
                else:
                    with lock:
                        counts["held_back"] += 1
                        report()
            tick += 1
    stop.wait()
    deadline = time.monotonic() + 10.0
    while time.monotonic() < deadline and counts["acked"] < counts["sent"]:
        time.sleep(0.1)
    for client, _ in fleet:
        client.disconnect()
        client.loop_stop()


def _start_load(
    cluster: RabbitCluster, vehicles: list[str], bodies: list[list[str]], rate: float, payload: str = "json"
) -> _Load:
    ctx = mp.get_context("spawn")
    n = math.ceil(len(vehicles) / VEHICLES_PER_GENERATOR)
    load = _Load(counters=ctx.Array("q", 3 * n, lock=False), stop=ctx.Event())
    start_ms = int(time.time() * 1000) - (1000 if 0 < rate <= 1 else DATA_START_MS_AGO)
    share = math.ceil(len(vehicles) / n)
    for slot in range(n):
        process = ctx.Process(
            target=_drive,
            args=(
                slot,
                cluster.mqtt_ports,
                cluster.secret,
                vehicles[slot * share : (slot + 1) * share],
                bodies,
                start_ms,
                rate,
                load.counters,
                load.stop,
                payload,
            ),
            daemon=True,
        )
        process.start()
        load.processes.append(process)
    deadline = time.monotonic() + 60 + len(vehicles) / 20
    while load.connected_vehicles() < len(vehicles):
        if time.monotonic() > deadline or not all(p.is_alive() for p in load.processes):
            _stop_load(load)
            raise RuntimeError(f"only {load.connected_vehicles()} of {len(vehicles)} vehicles connected")
        time.sleep(0.1)
    return load


def _stop_load(load: _Load) -> None:
    load.stop.set()
    for process in load.processes:
        process.join(30)
        if process.is_alive():
            process.kill()
            process.join()


# ------------------------------------------------------------------------------------------------- the broker alone
class _AckOnly:
    """A consumer per partition queue, in threads of this process, that only acknowledges what it receives."""

    def __init__(self, cluster: RabbitCluster, partitions: int):
        self.consumed = [0] * partitions
        self._stop = threading.Event()
        self._threads = [
            threading.Thread(target=self._consume, args=(cluster.amqp_url(p % 3), p), daemon=True)
            for p in range(partitions)
        ]
        self._ready = threading.Barrier(partitions + 1)
        for thread in self._threads:
            thread.start()
        self._ready.wait(60)

    def _consume(self, url: str, partition: int) -> None:
        connection = pika.BlockingConnection(pika.URLParameters(url))
        channel = connection.channel()
        channel.basic_qos(prefetch_count=10 * ACK_EVERY)
        last = [0]

        def on_message(ch, method, properties, body):
            self.consumed[partition] += 1
            last[0] = method.delivery_tag
            if self.consumed[partition] % ACK_EVERY == 0:
                ch.basic_ack(last[0], multiple=True)
                last[0] = 0

        channel.basic_consume(partition_queue(partition), on_message)
        self._ready.wait(60)
        while not self._stop.is_set():
            connection.process_data_events(time_limit=FLUSH_S)
            if last[0]:
                channel.basic_ack(last[0], multiple=True)
                last[0] = 0
        connection.close()

    def close(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(30)


# ------------------------------------------------------------------------------------------------- workers
class _Workers:
    """`count` `roadgrip worker` processes on `database_url`, logging to files in `workdir`."""

    def __init__(self, cluster: RabbitCluster, database_url: str, partitions: int, count: int, workdir: Path):
        env = {**os.environ, "ROADGRIP_RATE_LIMIT_SAMPLES_PER_S": "0"}  # the vehicles run faster than real time
        self.logs = [workdir / f"worker-{count}-{k}.log" for k in range(count)]
        self.procs = []
        for k, log_path in enumerate(self.logs):
            brokers = [arg for i in range(3) for arg in ("--broker", cluster.amqp_url((k + i) % 3))]
            with open(log_path, "wb") as log:
                self.procs.append(
                    subprocess.Popen(
                        [
                            str(ROADGRIP),
                            "worker",
                            "--database",
                            database_url,
                            "--partitions",
                            str(partitions),
                            *brokers,
                        ],
                        stdout=log,
                        stderr=subprocess.STDOUT,
                        env=env,
                    )
                )

    def wait_ready(self, timeout_s: float = 180.0) -> None:
        deadline = time.monotonic() + timeout_s
        for proc, log_path in zip(self.procs, self.logs):
            while "worker consuming" not in log_path.read_text():
                if proc.poll() is not None or time.monotonic() > deadline:
                    raise RuntimeError(f"worker not ready ({log_path}):\n{log_path.read_text()[-2000:]}")
                time.sleep(0.2)

    def pids(self) -> set[str]:
        return {str(p.pid) for p in self.procs}

    def cpu_s(self) -> float:
        """CPU seconds (user + system) the worker processes have used so far, from /proc (Linux)."""
        ticks = os.sysconf("SC_CLK_TCK")
        total = 0
        for proc in self.procs:
            # the fields after the command's name, which is in parentheses: utime and stime are the 12th and 13th
            fields = Path(f"/proc/{proc.pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += int(fields[11]) + int(fields[12])
        return total / ticks

    def stop(self) -> None:
        for proc in self.procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
        for proc in self.procs:
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


class _Database:
    def __init__(self, url: str):
        self.conn = psycopg.connect(
            make_url(url).set(drivername="postgresql").render_as_string(hide_password=False), autocommit=True
        )

    def stored(self) -> int:
        return self.conn.execute("SELECT count(*) FROM telemetry").fetchone()[0]

    def held(self) -> dict[str, int]:
        """Partitions taken, by the pid of the worker that took them last."""
        held: dict[str, int] = {}
        for (owner,) in self.conn.execute("SELECT owner FROM partition_owners").fetchall():
            pid = owner.rsplit(":", 1)[1]
            held[pid] = held.get(pid, 0) + 1
        return held

    def close(self) -> None:
        self.conn.close()


def _spread(held: dict[str, int], pids: set[str], partitions: int) -> bool:
    """Every partition taken by a running worker, none holding more than its share."""
    counts = [held.get(pid, 0) for pid in pids]
    return sum(counts) == partitions and max(counts) <= math.ceil(partitions / len(pids))


# ------------------------------------------------------------------------------------------------- the run
def _ready_messages(cluster: RabbitCluster, partitions: int) -> int:
    connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(0)))
    try:
        channel = connection.channel()
        return sum(
            channel.queue_declare(partition_queue(p), passive=True).method.message_count for p in range(partitions)
        )
    finally:
        connection.close()


def _purge(cluster: RabbitCluster, partitions: int) -> None:
    connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(0)))
    try:
        channel = connection.channel()
        for p in range(partitions):
            channel.queue_purge(partition_queue(p))
    finally:
        connection.close()


def _window(seconds: float, read: Callable[[], tuple[int, ...]], tick: Callable[[float], None]):
    """`read()` at the start and the end of a window of `seconds`, and the window's length; `tick(fraction)` every
    second."""
    first, started = read(), time.monotonic()
    while (elapsed := time.monotonic() - started) < seconds:
        tick(elapsed / seconds)
        time.sleep(min(1.0, seconds - elapsed))
    last = read()
    return first, last, time.monotonic() - started


def run_cluster_bench(bench: ClusterBench, progress: Progress = lambda message, fraction: None) -> dict:
    """Run every case of `bench` (module docstring) and return the results (JSON-able)."""
    from roadgrip.bench.sim import machine_description
    from roadgrip.cloud.storage.local_postgres import LocalPostgres

    started = time.monotonic()
    cases = 1 + len(bench.workers)
    vehicles = [f"bench{k:05d}" for k in range(bench.vehicles)]
    progress("simulating the telemetry", 0.0)
    bodies = sample_bodies()
    result: dict = {
        "config": {**asdict(bench), "samples_per_message": SAMPLES_PER_MESSAGE, "in_flight": IN_FLIGHT},
        "machine": machine_description(),
    }
    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-cluster-") as tmp, LocalPostgres() as postgres:
        workdir = Path(tmp)
        progress("starting 3 RabbitMQ nodes and PostgreSQL", 0.0)
        (workdir / "rabbit").mkdir()
        cluster = RabbitCluster(workdir / "rabbit", vehicles, bench.partitions, secrets.token_urlsafe(16))
        try:
            cluster.start()
            cluster.setup()
            result["cluster_start_s"] = round(time.monotonic() - started, 1)

            def fraction(case: int, within: float) -> float:
                return (case + within) / cases

            progress("the broker alone: vehicles connecting", fraction(0, 0))
            consumers = _AckOnly(cluster, bench.partitions)
            load = _start_load(cluster, vehicles, bodies, rate=0.0, payload=bench.payload)
            try:
                time.sleep(WARM_UP_S)
                (acked0, consumed0), (acked1, consumed1), took = _window(
                    bench.seconds,
                    lambda: (load.acked_messages(), sum(consumers.consumed)),
                    lambda f: progress("the broker alone: ack-only consumers", fraction(0, f)),
                )
            finally:
                _stop_load(load)
                consumers.close()
            result["broker"] = {
                "pubacked_messages_per_s": (acked1 - acked0) / took,
                "pubacked_samples_per_s": SAMPLES_PER_MESSAGE * (acked1 - acked0) / took,
                "consumed_messages_per_s": (consumed1 - consumed0) / took,
                "window_s": took,
            }
            _purge(cluster, bench.partitions)
            result["workers"] = []
            for case, count in enumerate(bench.workers, start=1):
                result["workers"].append(
                    _worker_case(
                        bench,
                        count,
                        cluster,
                        postgres,
                        vehicles,
                        bodies,
                        workdir,
                        lambda message, f, case=case: progress(message, fraction(case, f)),
                    )
                )
                _purge(cluster, bench.partitions)
        finally:
            progress("stopping the cluster", 1.0)
            cluster.stop()
    result["elapsed_s"] = round(time.monotonic() - started, 1)
    return result


def _worker_case(
    bench: ClusterBench,
    count: int,
    cluster: RabbitCluster,
    postgres,
    vehicles: list[str],
    bodies: list[list[str]],
    workdir: Path,
    progress: Progress,
) -> dict:
    name = f"{count} worker" + ("s" if count > 1 else "")
    url = postgres.create_database(f"bench_{count}_workers")
    db = _Database(url)
    progress(f"{name}: starting", 0.0)
    workers = _Workers(cluster, url, bench.partitions, count, workdir)
    load = None
    try:
        workers.wait_ready()
        progress(f"{name}: vehicles connecting", 0.0)
        load = _start_load(cluster, vehicles, bodies, bench.rate, bench.payload)
        waited = time.monotonic()
        spread_s = None
        while time.monotonic() - waited < SPREAD_WAIT_S:
            if _spread(db.held(), workers.pids(), bench.partitions):
                spread_s = time.monotonic() - waited
                break
            progress(f"{name}: waiting for the partitions to spread", 0.0)
            time.sleep(0.5)
        time.sleep(WARM_UP_S)
        ready0 = _ready_messages(cluster, bench.partitions)
        (stored0, acked0, held0, cpu0), (stored1, acked1, held1, cpu1), took = _window(
            bench.seconds,
            lambda: (db.stored(), load.acked_messages(), load.held_back(), workers.cpu_s()),
            lambda f: progress(f"{name}: measuring", f),
        )
        ready1 = _ready_messages(cluster, bench.partitions)
        held = db.held()
    finally:
        if load is not None:
            _stop_load(load)
        workers.stop()
        db.close()
    return {
        "workers": count,
        "stored_samples_per_s": (stored1 - stored0) / took,
        "worker_cpu_s": cpu1 - cpu0,
        # stored samples per second of the workers' own CPU time: samples/s per worker core
        "stored_samples_per_worker_cpu_s": (stored1 - stored0) / max(cpu1 - cpu0, 1e-9),
        "offered_samples_per_s": None if not bench.rate else SAMPLES_PER_MESSAGE * bench.rate * bench.vehicles,
        "pubacked_samples_per_s": SAMPLES_PER_MESSAGE * (acked1 - acked0) / took,
        "held_back_messages": held1 - held0,
        "ready_messages_start": ready0,
        "ready_messages_end": ready1,
        "stored_total": stored1,
        "spread_s": spread_s,
        "partitions_held": sorted((held.get(pid, 0) for pid in workers.pids()), reverse=True),
        "window_s": took,
    }


def format_cluster_bench(result: dict):
    """The results as a rich Table: a row per case, rates in samples per second."""
    from rich.table import Table

    config = result["config"]
    table = Table(
        title=f"roadgrip bench cluster: {config['vehicles']} vehicles, {config['partitions']} partitions, "
        f"{config['seconds']:.0f} s a case",
        caption="samples/s, except the queue (messages ready at "
        "the window's start and end) and held back (messages vehicles skipped: 10 unacknowledged)",
    )
    columns = ("case", "offered", "PUBACKed", "stored", "per worker core", "queue", "held back", "partitions", "spread")
    for column in columns:
        table.add_column(column, justify="left" if column == "case" else "right")
    broker = result["broker"]
    table.add_row(
        "broker",
        "max",
        f"{broker['pubacked_samples_per_s']:,.0f}",
        f"{SAMPLES_PER_MESSAGE * broker['consumed_messages_per_s']:,.0f} acked",
        "",
        "",
        "",
        "",
        "",
    )
    for case in result["workers"]:
        offered = "max" if case["offered_samples_per_s"] is None else f"{case['offered_samples_per_s']:,.0f}"
        spread = f"> {SPREAD_WAIT_S:.0f} s" if case["spread_s"] is None else f"{case['spread_s']:.0f} s"
        table.add_row(
            f"{case['workers']} worker" + ("s" if case["workers"] > 1 else ""),
            offered,
            f"{case['pubacked_samples_per_s']:,.0f}",
            f"{case['stored_samples_per_s']:,.0f}",
            f"{case['stored_samples_per_worker_cpu_s']:,.0f}",
            f"{case['ready_messages_start']:,} > {case['ready_messages_end']:,}",
            f"{case['held_back_messages']:,}",
            "/".join(map(str, case["partitions_held"])),
            spread,
        )
    return table


def write_json(result: dict, path: Path) -> None:
    path.write_text(json.dumps(result, indent=1))
