"""serve's MQTT intake of edge vehicles' messages (roadgrip/cloud/serve/edge_intake.py) on a real service and storage:
a batch is stored in one transaction and handed to the map in one call, each observation once (a repeat in the same
batch, one stored earlier, one stored before a restart), a broken message reported and acknowledged, every message
acknowledged only after its batch; a full queue defers to the broker (Busy) while paho's network thread goes on."""

from __future__ import annotations

import threading
import time

import h3
import orjson
from service_fixtures import running_cloud

from roadgrip.cloud.serve.edge_intake import EdgeIntake
from roadgrip.cloud.transport.mosquitto import ManagedBroker
from roadgrip.cloud.transport.mqtt import MqttClient, VehicleClient, observations_topic

NOW_MS = int(time.time() * 1000) - 600_000
LAT, LON = 59.91, 10.75
STEP_MS = 120_000  # a vehicle's observations this far apart are passes of their own (the pass gap is less)


def observation(vehicle_id: str, last_ms: int, mu: float = 0.2) -> dict:
    return {
        "vehicle_id": vehicle_id,
        "h3_cell": h3.latlng_to_cell(LAT, LON, 10),
        "first_ms": last_ms - 4_000,
        "last_ms": last_ms,
        "latitude_deg": LAT,
        "longitude_deg": LON,
        "mu": mu,
        "mu_lower": mu - 0.05,
        "mu_upper": mu + 0.05,
        "mu_proven": None,
        "excited": True,
        "n_estimates": 40,
        "n_excited": 12,
        "evidence": ["abs"],
        "channels": [],
        "vehicle_class": "paper-suv",
        "estimator": "pmf",
    }


def heartbeat(vehicle_id: str, timestamp_ms: int) -> dict:
    return {
        "vehicle_id": vehicle_id,
        "timestamp_ms": timestamp_ms,
        "latitude_deg": LAT,
        "longitude_deg": LON,
        "n_samples": 3000,
        "n_observations": 2,
        "outbox_pending": 0,
        "outbox_dropped": 0,
    }


class Acks:
    """The ack callables of submitted messages, and which were called (and how often)."""

    def __init__(self):
        self.calls: dict[int, int] = {}

    def make(self, k: int):
        self.calls.setdefault(k, 0)

        def ack():
            self.calls[k] += 1

        return ack


def submit_all(intake: EdgeIntake, acks: Acks, messages: list[tuple[str, str, dict | bytes]]) -> None:
    for k, (vehicle_id, kind, body) in enumerate(messages):
        payload = body if isinstance(body, bytes) else orjson.dumps(body)
        intake.submit(vehicle_id, kind, payload, acks.make(k))


def test_a_batch_is_stored_and_mapped_once_per_observation_and_acknowledged_after(tmp_path):
    url = f"sqlite:///{tmp_path / 'db.sqlite'}"
    with running_cloud(url, tmp_path) as (service, _):
        service.observations([observation("car-a", NOW_MS)])  # stored before, over HTTP
        rejected = []
        intake = EdgeIntake(service.settings, service.edge_messages, lambda v, e: rejected.append((v, e)))
        messages = [
            ("car-a", "observations", observation("car-a", NOW_MS)),  # stored before
            ("car-a", "observations", observation("car-a", NOW_MS + STEP_MS)),
            ("car-a", "observations", observation("car-a", NOW_MS + STEP_MS)),  # delivered again, same batch
            ("car-b", "observations", [observation("car-b", NOW_MS), observation("car-b", NOW_MS + STEP_MS)]),
            ("car-b", "observations", {**observation("car-b", NOW_MS + 2 * STEP_MS), "mu": "low"}),  # broken
            ("car-a", "heartbeat", heartbeat("car-a", NOW_MS)),
            ("car-a", "heartbeat", heartbeat("car-a", NOW_MS)),
            ("car-b", "observations", b"not json"),
        ]
        acks = Acks()
        submit_all(intake, acks, messages)  # before the worker runs: they wait in the queue, one batch
        assert intake.backlog == len(messages) and not any(acks.calls.values())
        intake.start()
        intake.stop()
        assert acks.calls == dict.fromkeys(range(len(messages)), 1)
        counts = intake.counts
        assert counts["batches"] == 1 and counts["largest_batch"] == len(messages)
        assert (counts["observations_received"], counts["observations_stored"]) == (5, 3)
        assert counts["observations_duplicates"] == 2
        assert (counts["heartbeats_received"], counts["heartbeats_stored"], counts["heartbeats_duplicates"]) == (
            2,
            1,
            1,
        )
        assert counts["messages_rejected"] == 2 and [v for v, _ in rejected] == ["car-b", "car-b"]
        assert rejected[0][1][0]["field"] == "mu"
        stored = {(o["vehicle_id"], o["last_ms"]) for o in service.storage.observations_since(0)}
        assert stored == {
            ("car-a", NOW_MS),
            ("car-a", NOW_MS + STEP_MS),
            ("car-b", NOW_MS),
            ("car-b", NOW_MS + STEP_MS),
        }
        assert len(service.storage.latest_heartbeats()) == 1
        # the map took each new observation once: the one over HTTP, then the batch's three
        assert service.fanout.observation_latency.since_start()["n"] == 4
        (cell,) = service.friction_map.cells(service.fanout.now_ms())
        assert cell.n_passes == 4 and cell.n_vehicles == 2

    with running_cloud(url, tmp_path) as (service, _):  # a restart: the same messages again are all duplicates
        assert service.friction_map.cells(service.fanout.now_ms())[0].n_passes == 4  # restored from storage
        intake = EdgeIntake(service.settings, service.edge_messages, lambda v, e: None)
        acks = Acks()
        submit_all(intake, acks, messages[:4])
        intake.start()
        intake.stop()
        assert acks.calls == dict.fromkeys(range(4), 1)
        assert (intake.counts["observations_stored"], intake.counts["observations_duplicates"]) == (0, 5)
        assert service.fanout.observation_latency.since_start()["n"] == 0
        assert len(service.storage.observations_since(0)) == 4


def wait_until(condition, timeout_s: float = 30, msg=lambda: "") -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        assert time.monotonic() < deadline, f"condition not met in time {msg()}"
        time.sleep(0.02)


def test_a_full_queue_defers_to_the_broker_without_holding_the_network_thread(tmp_path):
    """A real Mosquitto and the service's MqttClient with a keepalive of 1 s (the broker drops a client silent for
    1.5 s); the store is held shut while 200 observations come, against a queue of 20 and a Receive Maximum of 50
    (above the queue on purpose: Busy is the bound that must hold). The handler never waits: the overflow is deferred,
    the connection stays up through the held store, and once the store opens every observation is stored once."""
    n, keepalive_s = 200, 1
    with (
        running_cloud(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path) as (service, _),
        ManagedBroker(tmp_path / "broker") as broker,
    ):
        broker.set_user("car-a", "secret-a", "vehicle")
        gate = threading.Event()

        def slow_store(observations, heartbeats):
            gate.wait()
            return service.edge_messages(observations, heartbeats)

        intake = EdgeIntake(service.settings, slow_store, lambda v, e: None, max_backlog=20, max_batch=5)
        intake.start()
        mqtt = MqttClient(
            broker.url,
            broker.service_user,
            broker.service_password,
            "service-under-test",
            on_telemetry=lambda *_: None,
            on_edge=intake.submit,
            room=intake.has_room,
            receive_maximum=50,
            keepalive_s=keepalive_s,
            redelivery_poll_s=0.05,
        )
        mqtt.connect()
        try:
            with VehicleClient(broker.url, "car-a", "secret-a") as car:
                for k in range(n):
                    car.publish(observations_topic("car-a"), orjson.dumps(observation("car-a", NOW_MS - k * STEP_MS)))
            wait_until(lambda: mqtt.deferred >= 50 - 20 - 5)  # the window beyond the queue and the batch in hand
            assert intake.backlog == 20
            time.sleep(3 * keepalive_s)  # the store stays shut: paho must keep the connection alive meanwhile
            assert mqtt.connected and mqtt.drops == 0 and mqtt.redeliveries == 0
            gate.set()
            wait_until(lambda: intake.counts["observations_stored"] == n)
            wait_until(lambda: intake.backlog == 0)
        finally:
            mqtt.close()
            intake.stop()
        assert mqtt.drops == 0 and mqtt.redeliveries >= 1
        stored = [o["last_ms"] for o in service.storage.observations_since(0)]
        assert sorted(stored) == sorted(NOW_MS - k * STEP_MS for k in range(n))  # each once, none lost
        assert intake.counts["observations_stored"] == n and intake.counts["batches_failed"] == 0


def test_put_edge_stores_a_key_given_twice_in_one_call_once(storage):
    new, beats = storage.put_edge(
        [observation("car-a", NOW_MS), observation("car-a", NOW_MS), observation("car-a", NOW_MS + 1)],
        [heartbeat("car-a", NOW_MS), heartbeat("car-a", NOW_MS)],
    )
    assert new == {("car-a", NOW_MS), ("car-a", NOW_MS + 1)} and beats == 1
    assert storage.observation_extent() == {"car-a": (2, NOW_MS, NOW_MS + 1)}
    assert storage.put_edge([observation("car-a", NOW_MS)], []) == (set(), 0)
