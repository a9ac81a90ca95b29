"""`roadgrip bench ingest --mode edge`: edge vehicles' friction observations (CONTRACTS 3.7) into `roadgrip serve`, as a
soak: what the service spends on them, beside what it spends on raw telemetry (roadgrip/bench/ingest.py, the same
service process and broker), so that the cloud's cores per vehicle can be compared at the map's level, and whether it
holds a fleet: every observation stored exactly once, the map updated in time, memory flat (docs/EDGE.md).

The service runs as its own process (ingest.py's `_Service`: `roadgrip serve` with its managed Mosquitto, SQLite in a
scratch folder, the map's clock on the data). `vehicles` registered vehicles, each its own MQTT connection with its own
credentials, all connected before the start, publish `rate_per_s` observations a second each (QoS 1) for `seconds`,
from ingest.py's load generator (`_generate`: processes of at most MQTT_CLIENTS_PER_PROCESS vehicles); the vehicles'
messages are spread evenly over the period (vehicle k of n sends at the start + (k / n + i) / rate_per_s), as a fleet's
passes end at any time. The observations are real: those the vehicle end (roadgrip/edge/agent.py) makes of the fleet
benchmark's drives (its scenario at seed 0, TEMPLATE_VEHICLES vehicles for TEMPLATE_DURATION_S, patches appearing
within its first 300 s), cycled over the bench's vehicles with live times: each message's last_ms is the time it is
due to leave (so each is its own key, stored once, and the bench knows every vehicle's keys).

It reports: observations sent, PUBACKed and stored; the vehicles whose stored observations are exactly those sent
(count, first and last last_ms; the key is unique), the misses (PUBACKed, not stored) and the duplicates the service
skipped (a message delivered again), the observations handed to the map (each stored one once); the latency from an
observation's last_ms (when it left) to the map updated with it (the service's histogram since the start, 10 ms bins);
every 5 s a timeline point (stored, the intake's queue, the service's RSS, the recent latency); the memory trend over
the second half (ingest.py's `memory_trend`); the CPU seconds of the service (its process and children, the broker
apart), of the broker and of the load generators, and what the rest of the machine used meanwhile (from /proc/stat).
"""

from __future__ import annotations

import os
import resource
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import orjson

from roadgrip.bench.ingest import IngestCase, _generate, _Service, drain, memory_trend
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.transport.mqtt import observations_topic

TEMPLATE_VEHICLES = 4
TEMPLATE_DURATION_S = 900.0


def observation_templates(seed: int = 0) -> list[dict]:
    """The observations the vehicle end makes of the fleet benchmark's drives (module docstring)."""
    # here, not at the top: each load-generator process imports this module (ObservationMessages), and these weigh
    from roadgrip.edge.agent import EdgeAgent
    from roadgrip.edge.outbox import Outbox
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, simulate_drives

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


@dataclass(frozen=True)
class ObservationMessages:
    """ingest.py's `Messages` for edge vehicles: one observation a message, `rate_per_s` a second per vehicle, the
    `vehicles` spread over the period; vehicle k's message i is templates[(k + i) % len] with last_ms its due time."""

    templates: list[dict]
    rate_per_s: float
    vehicles: int

    def ticks(self, seconds: float) -> int:
        return int(seconds * self.rate_per_s)

    def due_s(self, k: int, tick: int) -> float:
        return (k / self.vehicles + tick) / self.rate_per_s

    def last_ms(self, k: int, tick: int, base_ms: int) -> int:
        return base_ms + round(1000 * self.due_s(k, tick))

    def topic(self, vehicle_id: str) -> str:
        return observations_topic(vehicle_id)

    def lines(self, vehicle_id: str, k: int, tick: int, base_ms: int) -> list[str]:
        o = self.templates[(k + tick) % len(self.templates)]
        last = self.last_ms(k, tick, base_ms)
        body = {**o, "vehicle_id": vehicle_id, "first_ms": last - (o["last_ms"] - o["first_ms"]), "last_ms": last}
        return [orjson.dumps(body).decode()]


def _busy_s() -> float:
    """CPU seconds the whole machine spent busy so far (all cores; /proc/stat)."""
    fields = [int(v) for v in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    idle = fields[3] + fields[4]  # idle, iowait
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


def run_edge_case(vehicles: int, seconds: float, rate_per_s: float, templates: list[dict], progress=print) -> dict:
    """`vehicles` x `rate_per_s` observations a second for `seconds` into a `roadgrip serve` (module docstring)."""
    if not templates:
        raise ValueError("no observation templates: the drives made no observation")
    if rate_per_s <= 0 or int(seconds * rate_per_s) < 1:
        raise ValueError(
            f"need at least one observation per vehicle, got rate_per_s={rate_per_s!r}, seconds={seconds!r}"
        )
    messages = ObservationMessages(templates, rate_per_s, vehicles)
    case = IngestCase("mqtt", vehicles, seconds, batch=1)
    with tempfile.TemporaryDirectory(prefix="roadgrip-bench-edge-") as tmp:
        service = _Service(Path(tmp), True, None)
        try:
            registered, mqtt_url = service.register(vehicles)
            progress(f"edge: {vehicles} vehicles x {rate_per_s:g} observations/s for {seconds:.0f} s")
            timeline = []
            started = time.time()

            def record() -> None:  # every 5 s: what a soak must show flat
                h = service.health()
                p = h["pipeline"]
                timeline.append(
                    {
                        "t_s": round(time.time() - started, 1),
                        "stored": p["edge"]["observations_stored"],
                        "backlog": p["edge"]["backlog"],
                        "largest_batch": p["edge"]["largest_batch"],
                        "rss_mb": h["memory_rss_mb"],
                        "mqtt_unacknowledged": p["mqtt_unacknowledged"],
                        **(p.get("mqtt_flow") or {}),
                        **p["observation_latency"],
                    }
                )

            cpu_before, busy_before = service.cpu_s(), _busy_s()
            children_before = resource.getrusage(resource.RUSAGE_CHILDREN)
            load_before = os.getloadavg()
            load = _generate(case, {"mqtt_url": mqtt_url}, registered, messages, on_tick=record)
            record()
            # drain: everything acknowledged is stored and nothing waits in the intake
            drain_s = drain(
                lambda: service.health()["pipeline"]["edge"], "observations_stored", load["acknowledged"], poll_s=0.2
            )
            cpu_after, busy_after = service.cpu_s(), _busy_s()
            children_after = resource.getrusage(resource.RUSAGE_CHILDREN)
            load_after = os.getloadavg()
            health = service.health()
            storage = open_storage(f"sqlite:///{Path(tmp) / 'roadgrip.sqlite'}")  # as ingest.py reads it
            extent = storage.observation_extent()
            storage.close()
        finally:
            service.stop()
    n = messages.ticks(seconds)
    base_ms = load["base_ms"]
    exact = sum(
        extent.get(vid) == (n, messages.last_ms(k, 0, base_ms), messages.last_ms(k, n - 1, base_ms))
        for k, (vid, _) in enumerate(registered)
    )
    stored = sum(v[0] for v in extent.values())
    pipeline = health["pipeline"]
    latency = pipeline["observation_latency_since_start"]
    service_cpu = cpu_after["service"] - cpu_before["service"]
    broker_cpu = cpu_after["broker"] - cpu_before["broker"]
    generator_cpu = sum(
        getattr(children_after, f) - getattr(children_before, f) for f in ("ru_utime", "ru_stime")
    )  # the load generators: the children this process waited for
    machine_cpu = busy_after - busy_before
    return {
        "case": "edge-mqtt",
        "vehicles": vehicles,
        "seconds": seconds,
        "rate_per_vehicle_s": rate_per_s,
        "offered_per_s": vehicles * rate_per_s,
        "complete": load["generators_finished"] == load["generators"],
        "generators_finished": f"{load['generators_finished']} of {load['generators']}",
        "sent": load["sent"],
        "acknowledged": load["acknowledged"],
        "refused": load["refused"],
        "acked_s": round(load["acked_s"], 2),
        "stored": stored,
        "lost": load["acknowledged"] - stored,
        "vehicles_stored_exactly": exact,
        "duplicates_skipped": pipeline["edge"]["observations_duplicates"],
        "fanned_out": latency["n"],
        "rejected": pipeline["edge"]["messages_rejected"],
        "largest_batch": pipeline["edge"]["largest_batch"],
        "batches": pipeline["edge"]["batches"],
        "latency_p50_ms": latency["p50_ms"],
        "latency_p99_ms": latency["p99_ms"],
        "latency_over_max": latency["over_max"],
        "drain_s": round(drain_s, 2),
        "mqtt_flow": pipeline.get("mqtt_flow"),
        "generator_lag_max_s": round(load["generator_lag_max_s"], 2),
        "service_cpu_s": round(service_cpu, 2),
        "broker_cpu_s": round(broker_cpu, 2),
        "generator_cpu_s": round(generator_cpu, 2),
        "other_cpu_s": round(machine_cpu - service_cpu - broker_cpu - generator_cpu, 1),
        "machine_cpu_s": round(machine_cpu, 1),
        "loadavg_before": [round(v, 2) for v in load_before],
        "loadavg_after": [round(v, 2) for v in load_after],
        "service_cpu_ms_per_stored": 1000.0 * service_cpu / max(stored, 1),
        "broker_cpu_ms_per_stored": 1000.0 * broker_cpu / max(stored, 1),
        "rss_mb_end": health["memory_rss_mb"],
        **memory_trend(timeline),
        "timeline": timeline,
        "wall_s": round(time.time() - started, 1),
    }


def format_edge_case(r: dict) -> str:
    growth = r["rss_growth_mb_per_min"]
    memory = "-" if growth is None else f"{growth:+.1f} MB/min ({'flat' if r['memory_flat'] else 'growing'})"
    latency = "-" if r["latency_p50_ms"] is None else f"{r['latency_p50_ms']:,.0f} / {r['latency_p99_ms']:,.0f} ms"
    return "\n".join(
        [
            (
                f"edge over MQTT: {r['vehicles']:,} vehicles, {r['offered_per_s']:g} observations/s offered for "
                f"{r['seconds']:.0f} s"
            ),
            *([] if r["complete"] else [f"INCOMPLETE: load generators finished {r['generators_finished']}"]),
            (
                f"sent {r['sent']:,}, PUBACKed {r['acknowledged']:,}, stored {r['stored']:,}, lost {r['lost']:,}; "
                f"vehicles stored exactly as sent {r['vehicles_stored_exactly']:,} of {r['vehicles']:,}; duplicates "
                f"skipped {r['duplicates_skipped']:,}; handed to the map {r['fanned_out']:,}"
            ),
            (
                f"map updated after the observation left, p50 / p99: {latency}; stored {r['drain_s']:.1f} s after the "
                f"last PUBACK; largest batch {r['largest_batch']:,} messages; load generator's worst lag "
                f"{r['generator_lag_max_s']:.2f} s"
            ),
            (
                f"service RSS at half-time / end {r['rss_mb_half'] or 0:,.0f} / {r['rss_mb_end'] or 0:,.0f} MB, "
                f"second half {memory}"
            ),
            (
                f"CPU s: service {r['service_cpu_s']:.1f} ({r['service_cpu_ms_per_stored']:.3f} ms per stored "
                f"observation), broker {r['broker_cpu_s']:.1f} ({r['broker_cpu_ms_per_stored']:.3f} ms), load generators "
                f"{r['generator_cpu_s']:.1f}, rest of the machine {r['other_cpu_s']:.1f} of {r['machine_cpu_s']:.1f}; "
                f"load average before {r['loadavg_before'][0]:.2f}, after {r['loadavg_after'][0]:.2f}"
            ),
        ]
    )
