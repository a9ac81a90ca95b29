"""`roadgrip bench uplink`: what a vehicle sends in raw mode (wire-format samples, as `roadgrip fleet` publishes them
over MQTT: one JSON sample per message, 10 a second) against edge mode (`roadgrip edge`: friction observations and
heartbeats, roadgrip/edge/) on the same simulated drives, those of the fleet benchmark
(roadgrip/evaluation/fleet_benchmark.py: its scenario at `seed`, with `vehicles` and `duration_s`); and what one agent
process costs: CPU seconds and peak RSS (VmHWM) of a `roadgrip edge` process over one vehicle's whole drive (its
first vehicle's), start-up (imports, compiled code loaded from numba's cache) included, read by that process itself
at its end; and the agents' CPU per hour of driving once running (their samples through `EdgeAgent.feed`, in this
process, all vehicles).

Bytes are MQTT payload bytes as sent (no MQTT, TCP or TLS framing); per vehicle-hour means per hour of samples (a
vehicle's driving time), the same hours in both modes.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import orjson

from roadgrip.edge.agent import EdgeAgent
from roadgrip.edge.outbox import Outbox
from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, simulate_drives


@dataclass(frozen=True)
class UplinkResult:
    vehicles: int
    vehicle_hours: float
    raw_bytes: int
    raw_messages: int
    edge_bytes: int
    edge_messages: int
    edge_observations: int
    feed_cpu_s: float  # all agents' samples through EdgeAgent.feed, this process
    agent_samples: int  # of the one agent process measured
    agent_cpu_s: float  # that process's CPU, start-up included
    agent_max_rss_mb: float

    def per_vehicle_hour(self, value: float) -> float:
        return value / self.vehicle_hours

    def per_vehicle_s(self, value: float) -> float:
        return value / (self.vehicle_hours * 3600.0)


def run_uplink_bench(seed: int = 0, vehicles: int = 8, duration_s: float = 3600.0, estimator: str = "pmf"):
    scenario = make_scenario(seed, FleetConfig(vehicles=vehicles, duration_s=duration_s))
    start_ms = int(time.time() * 1000) - int(duration_s * 1000) - 60_000
    drives = simulate_drives(scenario, start_ms)
    rows = drives.table.to_pylist()
    by_vehicle: dict[str, list[dict]] = {}
    for row in rows:
        by_vehicle.setdefault(row["vehicle_id"], []).append(row)
    raw_bytes = sum(len(json.dumps(row)) for row in rows)  # as roadgrip fleet publishes a sample
    edge_bytes = edge_messages = observations = 0
    feed_cpu_s = 0.0
    with tempfile.TemporaryDirectory() as scratch:
        for vehicle_id, samples in sorted(by_vehicle.items()):
            outbox = Outbox(Path(scratch) / f"{vehicle_id}.sqlite")
            agent = EdgeAgent(vehicle_id, scenario.kinds[vehicle_id], load_estimator(estimator), outbox)
            started = time.process_time()
            for sample in samples:
                agent.feed(sample)
            agent.finish()
            feed_cpu_s += time.process_time() - started
            sent = outbox.oldest(outbox.pending)
            edge_bytes += sum(len(payload) for _, _, payload in sent)
            edge_messages += len(sent)
            observations += agent.observations
            outbox.close()
        first = min(by_vehicle)
        drive = Path(scratch) / "drive.ndjson"
        drive.write_bytes(b"".join(orjson.dumps(s) + b"\n" for s in by_vehicle[first]))
        cpu_s, rss_mb = _agent_process(drive, first, Path(scratch) / "agent", estimator)
    return UplinkResult(
        vehicles=len(by_vehicle),
        vehicle_hours=len(rows) / 36_000.0,
        raw_bytes=raw_bytes,
        raw_messages=len(rows),
        edge_bytes=edge_bytes,
        edge_messages=edge_messages,
        edge_observations=observations,
        feed_cpu_s=feed_cpu_s,
        agent_samples=len(by_vehicle[first]),
        agent_cpu_s=cpu_s,
        agent_max_rss_mb=rss_mb,
    )


# `roadgrip edge` in a child process that reports its own CPU and peak RSS at its end: a fork of this big process
# would count this process's pages in the child's getrusage maximum
_CHILD = """import json, sys, time
from roadgrip.cli import app
try:
    app(sys.argv[1:], standalone_mode=False)
finally:
    hwm = open('/proc/self/status').read().split('VmHWM:')[1].split()[0]
    print(json.dumps({'cpu_s': time.process_time(), 'hwm_kb': int(hwm)}), file=sys.stderr)
"""


def _agent_process(drive: Path, vehicle_id: str, state_dir: Path, estimator: str) -> tuple[float, float]:
    """(CPU seconds, peak RSS in MB) of one `roadgrip edge` process over the drive, no broker (the outbox keeps it)."""
    command = [sys.executable, "-c", _CHILD, "edge", "--vehicle-id", vehicle_id, "--input", str(drive)]
    command += ["--state-dir", str(state_dir), "--estimator", estimator]
    done = subprocess.run(command, check=True, capture_output=True, text=True)
    report = json.loads(done.stderr.strip().splitlines()[-1])
    return report["cpu_s"], report["hwm_kb"] / 1024.0


def format_uplink(r: UplinkResult) -> str:
    raw_h, edge_h = r.per_vehicle_hour(r.raw_bytes), r.per_vehicle_hour(r.edge_bytes)
    lines = [
        f"{r.vehicles} vehicles, {r.vehicle_hours:.2f} vehicle-hours of driving",
        "| mode | payload bytes per vehicle-hour | messages/s per vehicle |",
        "| --- | --- | --- |",
        f"| raw | {raw_h:,.0f} | {r.per_vehicle_s(r.raw_messages):.3f} |",
        f"| edge | {edge_h:,.0f} | {r.per_vehicle_s(r.edge_messages):.4f} |",
        f"edge / raw bytes: 1/{raw_h / max(edge_h, 1e-9):,.0f}; {r.edge_observations} observations",
        (
            f"agents running: {r.feed_cpu_s:.1f} s CPU for {r.vehicle_hours:.2f} h of driving "
            f"({r.feed_cpu_s / r.vehicle_hours:.1f} s per vehicle-hour)"
        ),
        (
            f"one roadgrip edge process: {r.agent_samples} samples ({r.agent_samples / 36_000:.2f} h of driving), "
            f"CPU {r.agent_cpu_s:.1f} s with start-up, peak RSS {r.agent_max_rss_mb:.0f} MB"
        ),
    ]
    return "\n".join(lines)
