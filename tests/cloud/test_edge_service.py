"""Edge vehicles against a real `serve` (CONTRACTS 3.7): an agent (roadgrip/edge/) publishes its observations to the
service's own Mosquitto with its vehicle's credentials; they are stored once, reach the map and raise a warning like
the raw telemetry of the same drive would. Over HTTP a bad observation is refused with one line naming the field."""

from __future__ import annotations

import json
import time

import orjson
import pytest
from broker_fixtures import wait_until
from drives import patch_cells, patch_drive
from service_fixtures import ADMIN, register, register_mqtt, running_cloud

from roadgrip.cloud.transport.mosquitto import mosquitto_available
from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.edge.run import run_agent
from roadgrip.edge.uplink import Uplink
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import PAPER_SUV

START_MS = int(time.time() * 1000) - 600_000


def _observations(tmp_path, vehicle_id: str) -> list[dict]:
    """The observations an agent makes of the icy patch drive."""
    outbox = Outbox(tmp_path / f"{vehicle_id}.sqlite")
    agent = EdgeAgent(vehicle_id, PAPER_SUV, load_estimator("pmf"), outbox)
    run_agent(agent, wire_samples(patch_drive(0.2, 1), vehicle_id, START_MS))
    return [orjson.loads(p) for _, topic, p in outbox.oldest(1000) if topic.endswith("/observations")]


def test_an_edge_vehicle_over_mqtt_reaches_the_map_and_raises_a_warning(tmp_path):
    assert mosquitto_available(), "mosquitto is not installed: run `bash scripts/install_system_deps.sh`"
    with running_cloud(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path, mqtt="managed") as (service, client):
        vehicle_id, secret, url = register_mqtt(client, "edge-car")
        outbox = Outbox(tmp_path / "edge" / "outbox.sqlite")
        agent = EdgeAgent(vehicle_id, PAPER_SUV, load_estimator("pmf"), outbox)
        uplink = Uplink(url, vehicle_id, secret, outbox, client_id=f"roadgrip-edge-{vehicle_id}")
        uplink.start()
        try:
            summary = run_agent(agent, wire_samples(patch_drive(0.2, 1), vehicle_id, START_MS), uplink, drain_s=20)
        finally:
            uplink.close()
        assert summary.pending == 0 and summary.observations > 0 and uplink.refused == 0
        # PUBACK comes from the broker before the service has stored the message: wait for every one
        wait_until(
            lambda: (
                len(service.storage.observations_since(0)) >= summary.observations
                and service.storage.latest_heartbeats()
            ),
            what="observations and the heartbeat stored",
        )
        assert len(service.storage.observations_since(0)) == summary.observations
        assert len(service.storage.latest_heartbeats()) == 1
        readers = client.post("/v1/readers", json={"name": "r"}, auth=ADMIN).json()
        warnings = client.get("/v1/warnings", auth=("r", readers["secret"])).json()["warnings"]
        cells = {w["roadgrip"]["cell"] for w in warnings}
        assert cells and cells <= patch_cells()
        features = client.get("/v1/map", auth=("r", readers["secret"])).json()["features"]
        low = [f for f in features if f["id"] in cells]
        assert low and all(f["properties"]["mu_upper"] < 0.4 for f in low)


def test_http_observations_are_stored_once_and_bad_ones_refused_naming_the_field(tmp_path):
    with running_cloud(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path) as (service, client):
        vehicle_id, secret = register(client, "edge-http")
        observations = _observations(tmp_path, vehicle_id)
        auth = (vehicle_id, secret)
        answer = client.post("/v1/observations", content=json.dumps(observations), auth=auth)
        assert answer.status_code == 200, answer.text
        assert answer.json() == {"received": len(observations), "stored": len(observations), "duplicates": 0}
        again = client.post("/v1/observations", content=json.dumps(observations[:1]), auth=auth).json()
        assert again == {"received": 1, "stored": 0, "duplicates": 1}
        assert len(service.storage.observations_since(0)) == len(observations)
        first = observations[0]
        for change, field in (
            ({"mu": 2.0}, "mu"),
            ({"mu_lower": first["mu_upper"] + 0.01}, "mu"),
            ({"h3_cell": "8a2a1072b59ffff"}, "latitude_deg"),
            ({"n_excited": first["n_estimates"] + 1}, "n_excited"),
            ({"evidence": ["vibes"]}, "evidence"),
            ({"vehicle_id": "someone-else"}, "vehicle_id"),
            ({"mu_uper": 0.5}, "mu_uper"),
        ):
            refused = client.post("/v1/observations", content=json.dumps(first | change), auth=auth)
            assert refused.status_code == 422, (change, refused.text)
            assert refused.json()["detail"]["field"] == field, refused.text
        assert client.post("/v1/observations", content=b"{not json", auth=auth).status_code == 400
        reader = client.post("/v1/readers", json={"name": "r"}, auth=ADMIN).json()
        assert (
            client.post("/v1/observations", content=json.dumps(first), auth=("r", reader["secret"])).status_code == 403
        )
        assert len(service.storage.observations_since(0)) == len(observations)


@pytest.mark.parametrize("missing", ["n_samples", "timestamp_ms"])
def test_a_heartbeat_without_a_field_is_refused(tmp_path, missing):
    with running_cloud(f"sqlite:///{tmp_path / 'db.sqlite'}", tmp_path) as (_, client):
        vehicle_id, secret = register(client, "edge-hb")
        beat = {
            "vehicle_id": vehicle_id,
            "timestamp_ms": START_MS,
            "latitude_deg": None,
            "longitude_deg": None,
            "n_samples": 10,
            "n_observations": 0,
            "outbox_pending": 0,
            "outbox_dropped": 0,
        }
        assert client.post("/v1/heartbeats", json=beat, auth=(vehicle_id, secret)).json()["stored"] == 1
        beat.pop(missing)
        refused = client.post("/v1/heartbeats", json=beat, auth=(vehicle_id, secret))
        assert refused.status_code == 422 and refused.json()["detail"]["field"] == missing
