"""The region fan-out of cluster mode against real servers (issue 17 item 3): a 3-node RabbitMQ 3.10 cluster
(roadgrip/cloud/transport/amqp.py `RabbitCluster`, started once for the module), PostgreSQL (conftest.py), two
`roadgrip worker` processes, vehicles publishing simulated drives over MQTT 3.1.1 QoS 1, and an MQTT 3.1.1 client
subscribed to the warnings topic.

- Vehicles in two distant regions: their estimates reach two region queues (chosen so by probing the broker's hash),
  each region's patch of low mu raises warnings, stored in PostgreSQL and published as DENMs on the MQTT warnings
  topic; the map the region owners saved, read back as an API replica would, shows the patch.
- kill -9 of the worker that owns a region's queue: the other worker takes the queue over, restores the region's map
  cells and active warnings from PostgreSQL, and vehicles that then brake on dry road over the whole stretch where the
  ice was cancel the warnings raised before the kill (stored, and published with the DENM's termination).
- A station's evidence published by an API replica with no broker reachable is given up at its deadline."""

from __future__ import annotations

import itertools
import json
import queue
import signal
import threading
import time
from pathlib import Path

import h3
import paho.mqtt.client as paho
import pika
import psycopg
import pymap3d
import pytest
from cluster_fixtures import WorkerProcess, node_killed, running_rabbit_cluster
from drives import PATCH_M, patch_drive
from paho.mqtt.enums import CallbackAPIVersion
from sqlalchemy.engine import make_url

from roadgrip.cloud.cluster.map_cells import region_of, stored_friction_map
from roadgrip.cloud.cluster.regions import RegionPublisher, publish_station_evidence
from roadgrip.cloud.localhost import free_ports
from roadgrip.cloud.pipeline.pipeline import MAX_ROUND_SAMPLES
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.transport.amqp import (
    ESTIMATES_EXCHANGE,
    HOST,
    SERVICE_USER,
    RabbitCluster,
    partition_queue,
    region_queue,
)
from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, telemetry_topic
from roadgrip.fleet.terminal import wire_samples
from roadgrip.sim.sensors import HEBEI_ORIGIN
from roadgrip.vehicle.params import PAPER_SUV

pytestmark = [pytest.mark.cluster, pytest.mark.timeout(900)]  # needs a local RabbitMQ cluster
PARTITIONS = 4
REGION_QUEUES = 4
WORKER_ENV = {"ROADGRIP_MAP_CLOCK": "data", "ROADGRIP_REGION_QUEUES": str(REGION_QUEUES)}  # the map on the data's clock
SETTINGS = Settings(map_clock="data")  # the workers' (environment below): the map's clock is the data's
START_MS = int(time.time() * 1000) - 3_600_000
TAKEOVER_LIMIT_S = 10.0
VEHICLES = [
    f"{tag}-{name}"
    for tag in "xyz"
    for name in ("ice1", "ice2", "close1", "ping", "dry0", "dry1", "dry2", "close2", "ice3", "close3")
]
# three dry vehicles braking 2 s apart prove grip from the patch's start to its end (255-300, 305-350, 355-400 m east),
# where the ice vehicles read low (256-401 m: on ice their braking lasts the patch); one alone proves its first 45 m, and
# a warning whose ice goes on past it stays (roadgrip/cloud/domain/places.py, the ice next door)
DRY_BRAKE_S = (10.5, 12.5, 14.5)
STREAMING = [f"s{k:02d}" for k in range(8)]  # vehicles of the mid-stream kill


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with running_rabbit_cluster(
        tmp_path_factory.mktemp("rabbit"), VEHICLES + STREAMING, PARTITIONS, "region-test-secret"
    ) as rabbit:
        yield rabbit


def queue_of_region(channel, region: str) -> int:
    """Which region queue the broker's consistent hash sends `region` to: a probe message, found by the queues'
    depths (a queue with single-active-consumer refuses basic.get), then purged."""
    channel.confirm_delivery()
    channel.basic_publish(ESTIMATES_EXCHANGE, region, b"probe")
    deep = [
        q for q in range(REGION_QUEUES) if channel.queue_declare(region_queue(q), passive=True).method.message_count
    ]
    for q in deep:
        channel.queue_purge(region_queue(q))
    assert len(deep) == 1, f"the probe for region {region} is in region queues {deep}"
    return deep[0]


def regions_on_distinct_queues(cluster: RabbitCluster, n: int) -> list[tuple[float, str, int]]:
    """Latitude shifts (the first 0) that put copies of the test road (at the Hebei origin) in `n` regions far apart
    on `n` different region queues: (shift in degrees, region, its queue) each."""
    connection = pika.BlockingConnection(pika.URLParameters(cluster.amqp_url(0)))
    channel = connection.channel()
    try:
        for q in range(REGION_QUEUES):
            channel.queue_purge(region_queue(q))
        for p in range(PARTITIONS):
            channel.queue_purge(partition_queue(p))
        found: list[tuple[float, str, int]] = []
        for shift_deg in [0, *range(5, 40)]:
            region = region_of(
                h3.latlng_to_cell(HEBEI_ORIGIN[0] + shift_deg, HEBEI_ORIGIN[1], SETTINGS.h3_resolution),
                SETTINGS.region_resolution,
            )
            q = queue_of_region(channel, region)
            if q not in {f[2] for f in found}:
                found.append((float(shift_deg), region, q))
            if len(found) == n:
                return found
        raise AssertionError(f"not {n} regions on distinct queues 0-40 degrees north of the origin: {found}")
    finally:
        connection.close()


def patch_cells(shift_deg: float) -> set[str]:
    """The cells of the road between the patch's ends (tests/cloud/drives.py), its copy shifted north by shift_deg."""
    cells = set()
    for east in range(int(PATCH_M[0]), int(PATCH_M[1]) + 1):
        lat, lon, _ = pymap3d.enu2geodetic(east, 0.0, 0.0, *HEBEI_ORIGIN, 0.0)
        cells.add(h3.latlng_to_cell(float(lat) + shift_deg, float(lon), SETTINGS.h3_resolution))
    return cells


def region_worker(cluster: RabbitCluster, nodes: list[int], database_url: str, log_path: Path) -> WorkerProcess:
    """A worker with the map on the data's clock and REGION_QUEUES region queues."""
    return WorkerProcess(cluster, nodes, database_url, log_path, PARTITIONS, env=WORKER_ENV)


class WarningsSubscriber:
    """An MQTT 3.1.1 client (the service user) subscribed to the warnings topic through node `node`."""

    def __init__(self, cluster: RabbitCluster, node: int):
        self.denms: queue.Queue = queue.Queue()
        self.all: list[dict] = []
        self.client = paho.Client(CallbackAPIVersion.VERSION2, client_id="warnings-reader", protocol=paho.MQTTv311)
        self.client.username_pw_set(SERVICE_USER, cluster.secret)
        subscribed = queue.Queue()
        self.client.on_subscribe = lambda c, u, mid, codes, props: subscribed.put(codes)
        self.client.on_message = lambda c, u, msg: self.denms.put(json.loads(msg.payload))
        self.client.connect(HOST, cluster.mqtt_ports[node])
        self.client.loop_start()
        self.client.subscribe(WARNINGS_TOPIC, qos=1)
        codes = subscribed.get(timeout=10)
        assert not any(code.is_failure for code in codes), codes

    def received(self) -> list[dict]:
        """Every DENM received so far."""
        while not self.denms.empty():
            self.all.append(self.denms.get())
        return self.all

    def close(self) -> None:
        self.client.disconnect()
        self.client.loop_stop()


def drive(
    cluster: RabbitCluster,
    runs: list[tuple[str, list[dict]]],
    node: int = 0,
    timeout_s: float = 60.0,
    pace_s: float = 0.0,
) -> None:
    """Each vehicle publishes its samples, ten a message, QoS 1 (the vehicles' k-th messages every `pace_s`, or at
    once); returns once every message is PUBACKed. A vehicle whose connection drops (RabbitMQ 3.10's MQTT plugin
    closes it on a quorum queue's nack during a leader election, docs/CLUSTER.md, Workers) connects again and paho
    sends what was not PUBACKed again."""
    clients = []
    for vehicle, samples in runs:
        client = paho.Client(CallbackAPIVersion.VERSION2, client_id=vehicle, protocol=paho.MQTTv311)
        client.username_pw_set(vehicle, cluster.secret)
        client.reconnect_delay_set(0.1, 1.0)
        connected, acked = threading.Event(), set()
        client.on_connect = lambda c, u, flags, rc, props, connected=connected: connected.set()
        client.on_publish = lambda c, u, mid, rc, props, acked=acked: acked.add(mid)
        client.connect(HOST, cluster.mqtt_ports[node])
        client.loop_start()
        assert connected.wait(10), f"{vehicle} not connected to node {node}"
        clients.append((client, set(), acked))
    started = time.monotonic()
    for m, k in enumerate(range(0, max(len(samples) for _, samples in runs), 10)):
        time.sleep(max(0.0, started + m * pace_s - time.monotonic()))
        for (vehicle, samples), (client, mids, _) in zip(runs, clients):
            if k < len(samples):  # one published while the connection is down is queued and sent on the next one
                mids.add(client.publish(telemetry_topic(vehicle), json.dumps(samples[k : k + 10]), qos=1).mid)
    deadline = time.monotonic() + timeout_s
    while not all(mids <= acked for _, mids, acked in clients):
        assert time.monotonic() < deadline, "messages not PUBACKed within the timeout"
        time.sleep(0.05)
    for client, _, _ in clients:
        client.disconnect()
        client.loop_stop()


def run_of(
    vehicle: str,
    patch_mu: float,
    seed: int,
    start_ms: int,
    shift_deg: float,
    brake_s: float = 10.5,
    first: int | None = None,
) -> tuple[str, list[dict]]:
    samples = wire_samples(patch_drive(patch_mu, seed, brake_s=brake_s), vehicle, start_ms)[:first]
    for s in samples:
        s["latitude_deg"] += shift_deg
        s["tcs_active"] = s["esc_active"] = False  # stated: pmf calibrates only where they are known
    return vehicle, samples


class Database:
    def __init__(self, url: str):
        self.conn = psycopg.connect(
            make_url(url).set(drivername="postgresql").render_as_string(hide_password=False), autocommit=True
        )

    def warnings(self) -> dict[str, dict]:
        rows = self.conn.execute("SELECT warning_id, cell, status, message FROM warnings").fetchall()
        return {w: {"cell": c, "status": s, "message": m} for w, c, s, m in rows}

    def region_owners(self) -> dict[int, tuple[int, str]]:
        rows = self.conn.execute("SELECT region_queue, epoch, owner FROM region_owners").fetchall()
        return {q: (epoch, owner) for q, epoch, owner in rows}

    def map_regions(self) -> set[str]:
        return {r for (r,) in self.conn.execute("SELECT DISTINCT region FROM map_cells").fetchall()}

    def close(self) -> None:
        self.conn.close()


def wait_for(what: str, predicate, timeout_s: float, logs) -> float:
    started = time.monotonic()
    while not predicate():
        if time.monotonic() - started > timeout_s:
            pytest.fail(
                f"{what} not within {timeout_s} s; worker logs:\n" + "\n---\n".join(log()[-4000:] for log in logs),
                pytrace=False,
            )
        time.sleep(0.2)
    return time.monotonic() - started


def patch_warnings(db: Database, cells: set[str], status: str = "active") -> dict[str, dict]:
    return {w: row for w, row in db.warnings().items() if row["cell"] in cells and row["status"] == status}


def test_regions_raise_publish_persist_and_move_to_another_worker_on_a_kill(cluster, postgres_database_url, tmp_path):
    found = regions_on_distinct_queues(cluster, 3)  # x: the home region, y: one with a patch too, z: a third
    shifts = {tag: shift for tag, (shift, _, _) in zip("xyz", found)}
    (_, home, home_queue), (_, far, far_queue), (_, _, third_queue) = found
    patches = {"x": patch_cells(0.0), "y": patch_cells(shifts["y"])}
    first = region_worker(cluster, [0, 1, 2], postgres_database_url, tmp_path / "worker-a.log")
    first.wait_ready()
    second = region_worker(cluster, [1, 2, 0], postgres_database_url, tmp_path / "worker-b.log")
    second.wait_ready()
    logs = (first.log, second.log)
    subscriber = WarningsSubscriber(cluster, 1)
    db = Database(postgres_database_url)
    storage = open_storage(postgres_database_url)
    try:
        # two vehicles brake on each region's patch of ice; two minutes later one vehicle in each region ends their
        # passes (the map's clock is the data's)
        drive(cluster, [run_of(f"{tag}-ice{k}", 0.2, k, START_MS, shifts[tag]) for tag in "xy" for k in (1, 2)])
        drive(cluster, [run_of(f"{tag}-close1", 0.9, 3, START_MS + 120_000, shifts[tag], first=5) for tag in "xyz"])
        wait_for("warnings on both patches", lambda: all(patch_warnings(db, patches[t]) for t in "xy"), 60, logs)
        raised = {t: patch_warnings(db, patches[t]) for t in "xy"}
        owners = db.region_owners()
        assert {home_queue, far_queue} <= owners.keys()  # the two regions' estimates reached their two queues
        wait_for("both regions' map cells saved", lambda: {home, far} <= db.map_regions(), 10, logs)
        # published: a DENM for each raised warning, on the MQTT warnings topic
        wait_for(
            "the DENMs",
            lambda: (
                len({d["denm"]["management"]["actionID"]["sequenceNumber"] for d in subscriber.received()})
                >= len(raised["x"]) + len(raised["y"])
            ),
            10,
            logs,
        )
        assert all(d["denm"]["situation"]["eventType"]["causeCode"] == 6 for d in subscriber.received())
        # the saved map, read back as an API replica would: the patch is there, slippery (once both vehicles' passes,
        # which may come through both workers, are in)
        now_ms = START_MS + 120_500

        def saved_patch_cells() -> dict[str, list]:
            cells = {c.cell: c for c in stored_friction_map(storage, SETTINGS, now_ms).cells(now_ms)}
            return {t: [cells[c] for c in patches[t] if c in cells] for t in "xy"}

        wait_for(
            "both ice vehicles in the saved map",
            lambda: all(any(c.n_vehicles >= 2 for c in on_patch) for on_patch in saved_patch_cells().values()),
            10,
            logs,
        )
        for t, on_patch in saved_patch_cells().items():
            assert min(c.mu for c in on_patch if c.mu is not None) < 0.4, t
            assert {c.status for c in on_patch} == {"measured"}, t
        # the first worker took the three queues; with two live workers it holds more than ceil(4 / 2) and releases
        # the one it took last, which the other takes at its next message (a vehicle at the road's start, off the
        # patch, in each region every 2 s of the test)
        pids = {str(first.proc.pid), str(second.proc.pid)}
        queues = (home_queue, far_queue, third_queue)
        pings = itertools.count()

        def spread() -> bool:
            owners = db.region_owners()
            if {owners[q][1].rsplit(":", 1)[1] for q in queues if q in owners} == pids:
                return True
            drive(
                cluster,
                [
                    run_of(f"{tag}-ping", 0.9, 3, START_MS + 130_000 + 5_000 * next(pings), shifts[tag], first=5)
                    for tag in "xyz"
                ],
            )
            time.sleep(2.0)
            return False

        took_s = wait_for("the region queues spread over both workers", spread, 60, logs)
        print(f"\nregion queues spread over the two workers {took_s:.1f} s after the warnings were stored")
        # kill -9 the owner of the home region's queue: the other worker takes it over and goes on from the database
        epoch, owner = db.region_owners()[home_queue]
        victim, survivor = (first, second) if owner.endswith(f":{first.proc.pid}") else (second, first)
        assert owner.endswith(f":{victim.proc.pid}")
        vehicles_before = {c.cell: c.n_vehicles for c in saved_patch_cells()["x"]}
        victim.proc.send_signal(signal.SIGKILL)
        victim.proc.wait()
        killed_at = time.monotonic()
        later = START_MS + 300_000
        dry = [
            run_of(f"{tag}-dry{k}", 0.9, 3, later, shifts[tag], b) for tag in "xy" for k, b in enumerate(DRY_BRAKE_S)
        ]
        drive(cluster, dry, node=2)
        drive(cluster, [run_of(f"{tag}-close2", 0.9, 3, later + 120_000, shifts[tag], first=5) for tag in "xy"], node=2)
        wait_for(
            "the home region's queue taken over",
            lambda: db.region_owners()[home_queue][1].endswith(f":{survivor.proc.pid}"),
            30,
            (survivor.log,),
        )
        took_s = time.monotonic() - killed_at
        print(
            f"\nregion queue {home_queue} taken over {took_s:.2f} s after the kill (a queue is taken at its first "
            f"delivery: the drives sent after the kill included)"
        )
        assert took_s < TAKEOVER_LIMIT_S
        # the dry vehicles braked over the patch the ice vehicles read low on: warnings raised before the kill are
        # cancelled by the new owner, which knows them only from the database (same warning and ActionID); the others
        # are still active
        for t in "xy":
            wait_for(
                f"a warning of region {t} raised before the kill cancelled",
                lambda t=t: any(db.warnings()[w]["status"] == "cancelled" for w in raised[t]),
                60,
                (survivor.log,),
            )
        time.sleep(2 * 1.0)  # the owner's next saves
        now = db.warnings()
        for t in "xy":
            for w, before in raised[t].items():
                event, was = now[w]["message"]["event"], before["message"]["event"]
                assert event["action_sequence_number"] == was["action_sequence_number"]
                assert (now[w]["status"], event["reason"]) in (("cancelled", "recovered"), ("active", "low friction"))
        assert db.region_owners()[home_queue][0] > epoch
        # the new owner's map went on from the saved cells: the vehicles before the kill are still counted
        wait_for(
            "the map saved by the new owner",
            lambda: any(
                c.n_vehicles > vehicles_before.get(c.cell, 0)
                for c in stored_friction_map(storage, SETTINGS).cells(later + 120_500)
                if c.cell in vehicles_before
            ),
            10,
            (survivor.log,),
        )
        after = {c.cell: c for c in stored_friction_map(storage, SETTINGS).cells(later + 120_500)}
        assert all(after[c].n_vehicles >= n for c, n in vehicles_before.items() if c in after)
        # and published the cancellations
        wait_for(
            "the cancellations' DENMs",
            lambda: any(d["denm"]["management"].get("termination") == "isCancellation" for d in subscriber.received()),
            10,
            (survivor.log,),
        )
        stats = survivor.stop()
        assert stats["region_publish_failures"] == 0 and stats["region_messages_published"] > 0
        print(
            f"longest time from a round's commit to its region messages' confirm (the crash window): "
            f"{stats['region_publish_window_s_max']:.3f} s"
        )
    finally:
        subscriber.close()
        storage.close()
        db.close()
        first.stop()
        second.stop()


def stream(cluster: RabbitCluster, vehicles: list[str], seconds: float, start_ms: int, node: int) -> None:
    """Each vehicle sends ten samples of steady driving (1 s of data, moving east) every 0.1 s for `seconds`, QoS 1,
    and waits for the last PUBACKs (as tests/cloud/cluster/test_worker.py's fleet, through one node)."""

    def samples(vehicle: str, m: int) -> list[dict]:
        w = 20.0 / PAPER_SUV.wheel_radius_m
        return [
            {
                "vehicle_id": vehicle,
                "timestamp_ms": start_ms + 1000 * m + 100 * k,
                "latitude_deg": 38.1,
                "longitude_deg": 114.5 + 2e-4 * (m + k / 10),
                "speed_mps": 20.0,
                "accel_lon_mps2": 0.0,
                "accel_lat_mps2": 0.0,
                "yaw_rate_radps": 0.0,
                "steering_wheel_angle_rad": 0.0,
                "wheel_speed_fl_radps": w,
                "wheel_speed_fr_radps": w,
                "wheel_speed_rl_radps": w,
                "wheel_speed_rr_radps": w,
                "abs_active": False,
                "acc_active": False,
                "tcs_active": False,
                "esc_active": False,
            }
            for k in range(10)
        ]

    messages = int(seconds / 0.1)
    drive(cluster, [(v, [s for m in range(messages) for s in samples(v, m)]) for v in vehicles], node=node, pace_s=0.1)


def test_estimates_stored_across_a_worker_kill_mid_stream_count_once_in_the_map(
    cluster, postgres_database_url, tmp_path
):
    """kill -9 of the worker that owns the region's queue while eight vehicles stream: afterwards every estimate stored
    is counted in the saved map at most once, and those the map misses (the crash window: rounds stored and not yet
    confirmed to the region stage when the worker died) are counted and printed."""
    regions_on_distinct_queues(cluster, 1)  # purges the queues
    first = region_worker(cluster, [0, 1, 2], postgres_database_url, tmp_path / "worker-a.log")
    first.wait_ready()
    second = region_worker(cluster, [1, 2, 0], postgres_database_url, tmp_path / "worker-b.log")
    second.wait_ready()
    logs = (first.log, second.log)
    db = Database(postgres_database_url)
    storage = open_storage(postgres_database_url)
    start_ms = START_MS + 1_000_000
    try:
        streaming = threading.Thread(target=stream, args=(cluster, STREAMING, 16.0, start_ms, 1))
        streaming.start()
        wait_for("a region queue taken", lambda: db.region_owners(), 20, logs)
        time.sleep(6.0)
        owner = min(db.region_owners().items())[1][1]  # of the (first) region queue the vehicles' region is on
        victim = first if owner.endswith(f":{first.proc.pid}") else second
        victim.proc.send_signal(signal.SIGKILL)
        victim.proc.wait()
        at_kill = dict(db.conn.execute("SELECT vehicle_id, max(timestamp_ms) FROM estimates GROUP BY vehicle_id"))
        streaming.join()

        def counts() -> tuple[int, int]:
            stored = db.conn.execute("SELECT count(*) FROM estimates WHERE h3_cell IS NOT NULL").fetchone()[0]
            now_ms = start_ms + 20_000
            mapped = sum(c.n_estimates for c in stored_friction_map(storage, SETTINGS, now_ms).cells(now_ms))
            return stored, mapped

        last = {"counts": (0, 0), "since": time.monotonic()}

        def settled() -> bool:  # unchanged for 3 s: the last pipeline rounds, region messages and saves (each 1 s) done
            now = counts()
            if now != last["counts"]:
                last.update(counts=now, since=time.monotonic())
            return time.monotonic() - last["since"] >= 3.0

        wait_for("the estimates and the map settled", settled, 60, logs)
        stored, mapped = last["counts"]
        print(
            f"\nworker kill mid-stream: {stored} estimates stored, {mapped} in the saved map, {stored - mapped} "
            f"missing (the crash window)"
        )
        # where they are missing: per cell, against the newest estimate of each vehicle stored when it was killed
        now_ms = start_ms + 20_000
        in_map = {c.cell: c.n_estimates for c in stored_friction_map(storage, SETTINGS, now_ms).cells(now_ms)}
        for cell, n, first_ms, last_ms in db.conn.execute(
            "SELECT h3_cell, count(*), min(timestamp_ms), max(timestamp_ms) FROM estimates GROUP BY h3_cell"
        ):
            if n != in_map.get(cell, 0):
                print(
                    f"  cell {cell}: {n} stored, {in_map.get(cell, 0)} in the map; stored estimates there from "
                    f"{first_ms - start_ms} to {last_ms - start_ms} ms of data; the vehicles' newest stored at the "
                    f"kill: {sorted(t - start_ms for t in at_kill.values())} ms"
                )
        assert stored > 0 and mapped <= stored  # nothing counted twice
        assert stored - mapped <= MAX_ROUND_SAMPLES  # at most the one round the killed worker had not yet published
    finally:
        storage.close()
        db.close()
        first.stop()
        second.stop()


def test_a_broker_node_killed_the_regions_go_on(cluster, postgres_database_url, tmp_path):
    """Node 0 carries the first worker's first connections (publisher, region queue 0, partitions) and some queue
    leaders; after its kill -9 a vehicle braking on each patch again refreshes the region's warnings, through the
    connections the workers moved to the other nodes. Node 0 is started again after the test (`node_killed`)."""
    found = regions_on_distinct_queues(cluster, 2)
    shifts = {tag: shift for tag, (shift, _, _) in zip("xy", found)}
    patches = {t: patch_cells(shifts[t]) for t in "xy"}
    first = region_worker(cluster, [0, 1, 2], postgres_database_url, tmp_path / "worker-a.log")
    first.wait_ready()
    second = region_worker(cluster, [1, 2, 0], postgres_database_url, tmp_path / "worker-b.log")
    second.wait_ready()
    logs = (first.log, second.log)
    db = Database(postgres_database_url)
    try:
        drive(cluster, [run_of(f"{tag}-ice1", 0.2, 1, START_MS, shifts[tag]) for tag in "xy"], node=1)
        drive(
            cluster, [run_of(f"{tag}-close1", 0.9, 3, START_MS + 120_000, shifts[tag], first=5) for tag in "xy"], node=1
        )
        wait_for("warnings on both patches", lambda: all(patch_warnings(db, patches[t]) for t in "xy"), 60, logs)
        before = {
            w: row["message"]["event"]["sequence_number"]
            for t in "xy"
            for w, row in patch_warnings(db, patches[t]).items()
        }
        with node_killed(cluster, 0):
            killed_at = time.monotonic()
            later = START_MS + 240_000  # within the warnings' validity
            drive(cluster, [run_of(f"{tag}-ice3", 0.2, 2, later, shifts[tag]) for tag in "xy"], node=2)
            drive(
                cluster,
                [run_of(f"{tag}-close3", 0.9, 3, later + 120_000, shifts[tag], first=5) for tag in "xy"],
                node=2,
            )

            def refreshed(t: str) -> bool:
                now = db.warnings()
                return any(
                    now[w]["message"]["event"]["sequence_number"] > n
                    for w, n in before.items()
                    if now[w]["cell"] in patches[t]
                )

            wait_for(
                "the warnings refreshed in both regions after the node's kill",
                lambda: all(refreshed(t) for t in "xy"),
                60,
                logs,
            )
            print(
                f"\nbroker node kill: both regions' warnings refreshed {time.monotonic() - killed_at:.1f} s after "
                f"it (the drives sent after the kill included)"
            )
    finally:
        db.close()
        first.stop()
        second.stop()


def test_station_evidence_with_no_broker_reachable_is_given_up_at_its_deadline():
    """Nothing listens on the brokers' ports (connections refused): the evidence is tried again, through one broker
    then the other, and given up at the deadline (TimeoutError, which the API answers with 503)."""
    publisher = RegionPublisher([f"amqp://{SERVICE_USER}:x@{HOST}:{port}/%2F" for port in free_ports(2)])
    cell = h3.latlng_to_cell(48.1, 11.5, SETTINGS.h3_resolution)
    row = {"station_id": "rws-1", "cell": cell, "timestamp_ms": START_MS, "mu": 0.2, "mu_lower": 0.1, "mu_upper": 0.3}
    started = time.monotonic()
    try:
        with pytest.raises(TimeoutError, match="not confirmed within 1.0 s"):
            publish_station_evidence(publisher, [row], SETTINGS.region_resolution, deadline_s=1.0)
    finally:
        publisher.close()
    assert time.monotonic() - started < 1.5
    assert publisher.failures >= 2 and publisher.published == 0  # tried again, through both brokers
