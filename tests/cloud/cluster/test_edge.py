"""Edge vehicles (CONTRACTS 3.7) against the local cluster (roadgrip/cloud/cluster/local.py: RabbitMQ nodes with the
MQTT plugin, PostgreSQL, a `roadgrip worker`, two `roadgrip api` replicas; started once for the module): observations
over MQTT 3.1.1 to a node reach the worker's edge consumer (roadgrip/cloud/cluster/edge.py), are stored once, and
their icy patch is warned about through an API replica; observations posted to one replica reach the map the other
serves; a vehicle cannot publish another's observations; `roadgrip fleet --mode edge` drives against the cluster."""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

import httpx
import orjson
import pytest
from drives import patch_cells, patch_drive
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cloud.cluster.local import LocalCluster
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.transport.amqp import RabbitCluster
from roadgrip.cloud.transport.mqtt import UserClient, errors_topic, heartbeat_topic, observations_topic
from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.edge.run import run_agent
from roadgrip.edge.uplink import Uplink
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import PAPER_SUV

pytestmark = [pytest.mark.cluster, pytest.mark.slow, pytest.mark.timeout(900)]  # needs a local RabbitMQ cluster
DRIVEN_AGO_MS = (
    60_000  # the drives end 30 s before now: well within a warning's validity (VALIDITY_S) on the wall clock
)
NORTH_DEG = 0.02  # the HTTP vehicle's copy of the drive, about 2.2 km north of the MQTT vehicle's
WAIT_S = 60.0
runner = CliRunner()


@pytest.fixture(scope="module")
def cluster():
    """The local cluster, in a new folder under the system's temporary directory (PostgreSQL runs as the user postgres
    there), removed after the module."""
    if not (RabbitCluster.bin_dir / "rabbitmq-server").exists():
        pytest.fail("rabbitmq-server is not installed: run `bash scripts/install_system_deps.sh`", pytrace=False)
    path = Path(tempfile.mkdtemp(prefix="roadgrip-edge-cluster-test-"))
    local = LocalCluster(path, nodes=2, workers=1, apis=2, partitions=2)
    try:
        local.start()
        yield local
    finally:
        local.stop()
        shutil.rmtree(path, ignore_errors=True)


@pytest.fixture(scope="module")
def storage(cluster):
    store = open_storage(cluster.database_url)
    yield store
    store.close()


def admin(cluster: LocalCluster) -> tuple[str, str]:
    return ("admin", cluster.admin_secret)


def register(cluster: LocalCluster, vehicle_id: str) -> dict:
    answer = httpx.post(
        f"{cluster.api_urls[0]}/v1/vehicles", json={"vehicle_id": vehicle_id}, auth=admin(cluster), timeout=30
    )
    assert answer.status_code == 201, answer.text
    return answer.json()


def drive(vehicle_id: str, north_deg: float = 0.0) -> list[dict]:
    """The icy patch drive (30 s), begun a minute ago, `north_deg` north of the test road."""
    samples = wire_samples(patch_drive(0.2, 1), vehicle_id, int(time.time() * 1000) - DRIVEN_AGO_MS)
    return [{**s, "latitude_deg": s["latitude_deg"] + north_deg} for s in samples]


def observations_of(storage, vehicle_id: str) -> list[dict]:
    return [o for o in storage.observations_since(0) if o["vehicle_id"] == vehicle_id]


def wait_for(predicate, what: str, timeout_s: float = WAIT_S):
    deadline = time.monotonic() + timeout_s
    while not (value := predicate()):
        assert time.monotonic() < deadline, f"{what} not within {timeout_s} s"
        time.sleep(0.5)
    return value


def low_cells(cluster: LocalCluster, replica: int, cells: set[str]) -> dict[str, float]:
    """The cells of `cells` in the map an API replica serves, with their mu_upper."""
    features = httpx.get(f"{cluster.api_urls[replica]}/v1/map", auth=admin(cluster), timeout=30).json()["features"]
    return {f["id"]: f["properties"]["mu_upper"] for f in features if f["id"] in cells}


def test_an_edge_agent_over_mqtt_is_stored_once_and_warned_about_through_a_replica(cluster, storage, tmp_path):
    vehicle = register(cluster, "edge-mq")
    outbox = Outbox(tmp_path / "outbox.sqlite")
    agent = EdgeAgent("edge-mq", PAPER_SUV, load_estimator("pmf"), outbox)
    run_agent(agent, drive("edge-mq"))  # out of coverage: every message waits in the outbox
    made = [p for _, topic, p in outbox.oldest(1000) if topic == observations_topic("edge-mq")]
    beats = [orjson.loads(p) for _, topic, p in outbox.oldest(1000) if topic == heartbeat_topic("edge-mq")]
    assert made and agent.observations == len(made) and beats
    uplink = Uplink(vehicle["mqtt_url"], "edge-mq", vehicle["secret"], outbox, protocol="3.1.1")
    uplink.start()
    try:
        deadline = time.monotonic() + WAIT_S
        while outbox.pending:
            assert time.monotonic() < deadline, f"{outbox.pending} messages not PUBACKed within {WAIT_S} s"
            uplink.pump()
            time.sleep(0.05)
    finally:
        uplink.close()
    assert uplink.refused == 0
    wait_for(
        lambda: (
            len(observations_of(storage, "edge-mq")) >= len(made)
            and any(h["vehicle_id"] == "edge-mq" for h in storage.latest_heartbeats())
        ),
        "observations and the heartbeat stored",
    )
    assert len(observations_of(storage, "edge-mq")) == len(made)
    beat = {**beats[-1], "timestamp_ms": beats[-1]["timestamp_ms"] + 1}
    with UserClient(vehicle["mqtt_url"], "edge-mq", vehicle["secret"], protocol="3.1.1").connect() as car:
        car.publish(observations_topic("edge-mq"), made[0])
        car.publish(heartbeat_topic("edge-mq"), orjson.dumps(beat))
    wait_for(
        lambda: any(h["timestamp_ms"] == beat["timestamp_ms"] for h in storage.latest_heartbeats()),
        "the later heartbeat",
    )
    assert len(observations_of(storage, "edge-mq")) == len(made)
    warnings = wait_for(
        lambda: httpx.get(f"{cluster.api_urls[1]}/v1/warnings", auth=admin(cluster), timeout=30).json()["warnings"],
        "a warning through the replica",
    )
    cells = {w["roadgrip"]["cell"] for w in warnings}
    assert cells and cells <= patch_cells()
    low = wait_for(lambda: low_cells(cluster, 1, cells), "the warned cells in the map")
    assert all(mu_upper < 0.4 for mu_upper in low.values()), low


def test_a_vehicle_cannot_publish_another_vehicles_observations(cluster, storage, tmp_path):
    owner, other = register(cluster, "edge-own"), register(cluster, "edge-other")
    outbox = Outbox(tmp_path / "outbox.sqlite")
    run_agent(EdgeAgent("edge-own", PAPER_SUV, load_estimator("pmf"), outbox), drive("edge-own", 2 * NORTH_DEG))
    payload = next(p for _, topic, p in outbox.oldest(1000) if topic == observations_topic("edge-own"))
    with UserClient(other["mqtt_url"], "edge-other", other["secret"], protocol="3.1.1").connect() as intruder:
        intruder.subscribe(errors_topic("edge-other"))
        # on its own topic, claiming the other vehicle in the body: refused by the consumer, on its errors topic
        intruder.publish(observations_topic("edge-other"), payload)
        topic, body = intruder.messages.get(timeout=WAIT_S)
        assert topic == errors_topic("edge-other")
        assert json.loads(body)["rejected"][0]["field"] == "vehicle_id"
        # on the other's topic: outside its topic permission, the broker closes its connection, no PUBACK
        with pytest.raises((TimeoutError, ConnectionError)):
            intruder.publish(observations_topic("edge-own"), payload, timeout_s=5)
    with UserClient(owner["mqtt_url"], "edge-own", owner["secret"], protocol="3.1.1").connect() as car:
        beat = {
            "vehicle_id": "edge-own",
            "timestamp_ms": int(time.time() * 1000),
            "latitude_deg": None,
            "longitude_deg": None,
            "n_samples": 0,
            "n_observations": 0,
            "outbox_pending": 0,
            "outbox_dropped": 0,
        }
        car.publish(heartbeat_topic("edge-own"), orjson.dumps(beat))
    wait_for(lambda: any(h["vehicle_id"] == "edge-own" for h in storage.latest_heartbeats()), "the owner's heartbeat")
    assert observations_of(storage, "edge-own") == [] and observations_of(storage, "edge-other") == []


def test_http_observations_through_one_replica_reach_the_map_the_other_serves(cluster, storage, tmp_path):
    vehicle = register(cluster, "edge-http")
    outbox = Outbox(tmp_path / "outbox.sqlite")
    samples = drive("edge-http", NORTH_DEG)
    run_agent(EdgeAgent("edge-http", PAPER_SUV, load_estimator("pmf"), outbox), samples)
    messages = outbox.oldest(1000)
    observations = [orjson.loads(p) for _, topic, p in messages if topic == observations_topic("edge-http")]
    beats = [orjson.loads(p) for _, topic, p in messages if topic == heartbeat_topic("edge-http")]
    assert observations and beats
    auth = ("edge-http", vehicle["secret"])
    post = httpx.post(f"{cluster.api_urls[0]}/v1/observations", json=observations, auth=auth, timeout=30)
    assert post.status_code == 200, post.text
    assert post.json() == {"received": len(observations), "stored": len(observations), "duplicates": 0}
    again = httpx.post(f"{cluster.api_urls[0]}/v1/observations", json=observations[:1], auth=auth, timeout=30)
    assert again.json() == {"received": 1, "stored": 0, "duplicates": 1}
    assert httpx.post(f"{cluster.api_urls[0]}/v1/heartbeats", json=beats, auth=auth, timeout=30).status_code == 200
    assert len(observations_of(storage, "edge-http")) == len(observations)
    excited = {o["h3_cell"] for o in observations if o["excited"] and o["mu_upper"] < 0.4}
    assert excited, "the drive's observations show no icy cell"
    low = wait_for(lambda: low_cells(cluster, 1, excited), "the observations' icy cells in the other replica's map")
    assert (
        set(low) == excited and excited.isdisjoint(patch_cells()) and all(mu_upper < 0.4 for mu_upper in low.values())
    ), low


def test_roadgrip_fleet_in_edge_mode_drives_against_the_cluster(cluster, storage, tmp_path):
    args = ["fleet", "--url", cluster.api_urls[0], "--admin-secret-file", str(cluster.admin_secret_file)]
    args += ["--vehicles", "2", "--speed", "50", "--duration", "60", "--per-slippery-patch", "1", "--prefix", "ef"]
    args += ["--mode", "edge", "--edge-state-dir", str(tmp_path)]
    args += [a for url in cluster.mqtt_urls for a in ("--mqtt", url)]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    out = " ".join(result.output.split())
    assert "lost 0 (still in the outboxes 0," in out and "MQTT 3.1.1" in out, out
    made = int(out.split("made ")[1].split(" observations")[0].replace(",", ""))
    assert made > 0
    stored = wait_for(
        lambda: (n := sum(1 for o in storage.observations_since(0) if o["vehicle_id"].startswith("ef-"))) >= made and n,
        "the fleet's observations stored",
    )
    assert stored == made
