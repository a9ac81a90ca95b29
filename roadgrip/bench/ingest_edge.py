"""`roadgrip bench ingest --mode edge`: what `roadgrip serve` spends on edge vehicles' friction observations (CONTRACTS
3.7), beside what it spends on raw telemetry (roadgrip/bench/ingest.py, the same service process and broker), so that
the cloud's cores per vehicle can be compared at the map's level (docs/EDGE.md).

The service runs as its own process (ingest.py's `_Service`: `roadgrip serve` with its managed Mosquitto, SQLite in a
scratch folder, the map's clock on the data); `vehicles` registered vehicles each publish `rate_per_s` observations a
second over MQTT (QoS 1, their own credentials, one load-generator process: this one) for `seconds`. The observations
are real: those the vehicle end (roadgrip/edge/agent.py) makes of the fleet benchmark's drives (its scenario at seed 0,
TEMPLATE_VEHICLES vehicles for TEMPLATE_DURATION_S, patches appearing within its first 300 s), cycled over the bench's vehicles with live times (each message
its own last_ms, so each is stored once). The bench waits until the service has stored every acknowledged one, and
reports the CPU seconds of the service (its process and children, the broker apart) and of the broker per stored
observation.
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import orjson

from roadgrip.bench.ingest import _Service
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.transport.mqtt import UserClient, observations_topic
from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, simulate_drives

TEMPLATE_VEHICLES = 4
TEMPLATE_DURATION_S = 900.0


def observation_templates(seed: int = 0) -> list[dict]:
    """The observations the vehicle end makes of the fleet benchmark's drives (module docstring)."""
    config = FleetConfig(
        vehicles=TEMPLATE_VEHICLES, duration_s=TEMPLATE_DURATION_S, appear_max_s=300.0, life_s=(400.0, 600.0)
    )  # the benchmark's patches, shortened to fit the shorter drives
    scenario = make_scenario(seed, config)
    drives = simulate_drives(scenario, int(time.time() * 1000) - 7_200_000)
    by_vehicle: dict[str, list[dict]] = {}
    for row in drives.table.to_pylist():
        by_vehicle.setdefault(row["vehicle_id"], []).append(row)
    templates = []
    with tempfile.TemporaryDirectory() as scratch:
        for vehicle_id, samples in sorted(by_vehicle.items()):
            outbox = Outbox(Path(scratch) / f"{vehicle_id}.sqlite")
            agent = EdgeAgent(vehicle_id, scenario.kinds[vehicle_id], load_estimator("pmf"), outbox)
            for sample in samples:
                agent.feed(sample)
            agent.finish()
            templates += [orjson.loads(p) for _, t, p in outbox.oldest(outbox.pending) if t.endswith("/observations")]
            outbox.close()
    return templates


def run_edge_case(vehicles: int, seconds: float, rate_per_s: float, templates: list[dict], progress=print) -> dict:
    """`vehicles` x `rate_per_s` observations a second for `seconds` into a `roadgrip serve` (module docstring)."""
    if not templates:
        raise ValueError("no observation templates: the drives made no observation")
    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-edge-") as tmp:
        service = _Service(Path(tmp), True, None)
        try:
            registered, mqtt_url = service.register(vehicles)
            clients = [UserClient(mqtt_url, vid, secret).connect() for vid, secret in registered]
            progress(f"edge: {vehicles} vehicles x {rate_per_s:g} observations/s for {seconds:.0f} s")
            cpu_before = service.cpu_s()
            started = time.time()
            ticks = int(seconds * rate_per_s)
            infos, k = [], 0
            for tick in range(ticks):
                wait = started + tick / rate_per_s - time.time()
                if wait > 0:
                    time.sleep(wait)
                now_ms = int(time.time() * 1000)
                for client, (vid, _) in zip(clients, registered):
                    o = templates[k % len(templates)]
                    k += 1
                    span = o["last_ms"] - o["first_ms"]
                    last = now_ms - 1000  # a vehicle's ticks are apart: each message stored once
                    body = {**o, "vehicle_id": vid, "first_ms": last - span, "last_ms": last}
                    infos.append(client.publish_nowait(observations_topic(vid), orjson.dumps(body)))
            deadline = time.time() + 120
            for info in infos:
                info.wait_for_publish(max(0.0, deadline - time.time()))
            acknowledged = sum(info.is_published() for info in infos) - sum(c.refused for c in clients)
            for c in clients:
                c.close()
            storage = open_storage(f"sqlite:///{Path(tmp) / 'roadgrip.sqlite'}")  # as ingest.py reads it
            ended = time.time()
            while (stored := len(storage.observations_since(0))) < acknowledged and time.time() - ended < 300:
                time.sleep(0.5)
            cpu_after = service.cpu_s()
            storage.close()
        finally:
            service.stop()
    service_cpu = cpu_after["service"] - cpu_before["service"]
    broker_cpu = cpu_after["broker"] - cpu_before["broker"]
    return {
        "case": "edge-mqtt",
        "vehicles": vehicles,
        "seconds": seconds,
        "offered_per_s": vehicles * rate_per_s,
        "sent": len(infos),
        "acknowledged": acknowledged,
        "stored": stored,
        "lost": acknowledged - stored,
        "service_cpu_s": round(service_cpu, 2),
        "broker_cpu_s": round(broker_cpu, 2),
        "service_cpu_ms_per_stored": 1000.0 * service_cpu / max(stored, 1),
        "broker_cpu_ms_per_stored": 1000.0 * broker_cpu / max(stored, 1),
        "wall_s": round(time.time() - started, 1),
    }


def format_edge_case(r: dict) -> str:
    return (
        f"edge over MQTT: {r['vehicles']} vehicles, {r['offered_per_s']:g} observations/s offered for "
        f"{r['seconds']:.0f} s: sent {r['sent']:,}, PUBACKed {r['acknowledged']:,}, stored {r['stored']:,}, lost "
        f"{r['lost']:,}; service CPU {r['service_cpu_s']:.1f} s ({r['service_cpu_ms_per_stored']:.3f} ms per stored "
        f"observation), broker CPU {r['broker_cpu_s']:.1f} s ({r['broker_cpu_ms_per_stored']:.3f} ms)"
    )
