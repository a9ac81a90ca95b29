"""`roadgrip bench failover`: a Jepsen-style count of what a fleet loses when parts of the cluster die
(docs/RELIABILITY.md, "Failover count").

What runs: the local cluster of `roadgrip cluster up` (roadgrip/cloud/cluster/local.py `LocalCluster`: 3 RabbitMQ
nodes, PostgreSQL, 2 workers, 1 API replica, `partitions` partition queues) and a simulated fleet
(roadgrip/fleet) driving at real time over MQTT 3.1.1, each vehicle's connection assigned node k mod 3 and failing
over to the others (roadgrip/fleet/transport.py). During the drive, at fixed offsets: worker 0 is killed (SIGKILL to
its process group), then RabbitMQ node `node` (SIGKILL of its beam.smp), then that node is started again.

What is counted, per vehicle: samples sent, PUBACKed and lost by the client (its own counts), stored (rows of
`telemetry` in PostgreSQL once the counts settle after the drive), PUBACKed but not stored (PUBACKed - stored, when
positive); the longest stall (the longest wall time in which its stored rows did not grow, from 2 s after the
drive's start to the vehicle's last sample, its road's end; from polling PostgreSQL every `poll_s`); for the
vehicles connected to the killed node whose road goes on after the kill, how long after the kill the first sample
produced after the kill was stored (`resumed_s`).

Partition moves, from the workers' logs after the drive started (`read_worker_logs`, `count_moves`): the takes
("partition N taken, epoch E"; the epochs order a partition's owners across workers), the spread rule's releases
("partition N released: ..."), the partition connections given up, and the live workers' count as each worker's
spread rule saw it change ("live workers: N"). The killed worker is not started again (`roadgrip cluster up` would:
that is a second change of the live workers, left out here), so the worker kill is the one real change of the live
workers during the drive; the node kill and restart are none.

Everything shares this machine's cores; the figures are one run's.
"""

from __future__ import annotations

import itertools
import math
import os
import re
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from datetime import datetime
from pathlib import Path

import psycopg
from sqlalchemy.engine import make_url

from roadgrip.cloud.cluster.local import LocalCluster
from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, timeline
from roadgrip.fleet.network import generated_network
from roadgrip.fleet.replay import replay
from roadgrip.fleet.transport import MqttTerminals, register_fleet

RESUME_TARGET_S = 10.0  # issue 25: every vehicle resumes within this of a node kill
SETTLE_QUIET_S = 5.0  # after the drive: the stored counts unchanged this long are taken as final

Progress = Callable[[str], None]

# the lines of the partition protocol in a worker's log (roadgrip/cloud/cluster/worker.py, spread.py), by event
_LOG_PATTERNS = [
    ("taken", re.compile(r"partition (?P<partition>\d+) taken, epoch (?P<epoch>\d+)$")),
    ("released", re.compile(r"partition (?P<partition>\d+) released: ")),
    ("releasing", re.compile(r"releasing partition (?P<partition>\d+): ")),
    ("lost", re.compile(r"partition (?P<partition>\d+): connection through broker \d+ lost")),
    ("live", re.compile(r"live workers: (?P<workers>\d+)$")),
]


@dataclass(frozen=True)
class FailoverBench:
    vehicles: int = 20
    duration_s: float = 100.0
    # offsets from the drive's start; the worker kill after the first spread (the first takes are held FRESH_S of
    # roadgrip/cloud/cluster/spread.py, 15 s, before worker 0 hands two partitions to worker 1)
    worker_kill_s: float = 30.0
    node_kill_s: float = 50.0
    node_restart_s: float = 70.0
    node: int = 1  # the RabbitMQ node killed (0, 1 or 2)
    partitions: int = 4
    poll_s: float = 0.25
    settle_timeout_s: float = 120.0
    seed: int = 0

    def __post_init__(self):
        if self.vehicles < 1:
            raise ValueError(f"vehicles must be at least 1, got {self.vehicles}")
        if not 0 < self.worker_kill_s < self.node_kill_s < self.node_restart_s < self.duration_s:
            raise ValueError(
                "need 0 < worker_kill_s < node_kill_s < node_restart_s < duration_s, got "
                f"{self.worker_kill_s}, {self.node_kill_s}, {self.node_restart_s}, {self.duration_s}"
            )
        if self.node not in (0, 1, 2):
            raise ValueError(f"node must be 0, 1 or 2 (the cluster has 3), got {self.node}")
        if self.partitions < 1 or self.poll_s <= 0:
            raise ValueError(f"partitions must be >= 1 and poll_s > 0, got {self.partitions}, {self.poll_s}")


class _StoredPoller:
    """Polls PostgreSQL every `poll_s` in a thread: per vehicle, its row count and newest timestamp, with the wall
    time of each poll (time.time())."""

    def __init__(self, database_url: str, poll_s: float):
        self.url = make_url(database_url).set(drivername="postgresql").render_as_string(hide_password=False)
        self.poll_s = poll_s
        self.polls: list[tuple[float, dict[str, tuple[int, int]]]] = []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stored-poller", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        """Idempotent."""
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join()

    def latest(self) -> dict[str, tuple[int, int]]:
        return self.polls[-1][1] if self.polls else {}

    def _run(self) -> None:
        with psycopg.connect(self.url, autocommit=True) as conn:
            while not self._stop.is_set():
                rows = conn.execute(
                    "SELECT vehicle_id, count(*), max(timestamp_ms) FROM telemetry GROUP BY vehicle_id"
                ).fetchall()
                self.polls.append((time.time(), {vid: (n, newest) for vid, n, newest in rows}))
                self._stop.wait(self.poll_s)


def _longest_stall(polls, vehicle_id: str, start: float, end: float) -> float:
    """The longest wall time within [start, end] in which the vehicle's stored rows did not grow."""
    grew, previous = [start], 0
    for t, counts in polls:
        n = counts.get(vehicle_id, (0, 0))[0]
        if start <= t <= end and n > previous:
            grew.append(t)
        previous = n
    grew.append(end)
    return max(b - a for a, b in itertools.pairwise(grew))


def _resumed(polls, vehicle_id: str, killed_at: float) -> float | None:
    """Seconds from `killed_at` to the first poll that found a sample of the vehicle produced after it."""
    for t, counts in polls:
        if t >= killed_at and counts.get(vehicle_id, (0, 0))[1] > killed_at * 1000:
            return t - killed_at
    return None


def _parse_time(stamp: str) -> float | None:
    """A log line's `asctime` (local time, as logging writes it) as time.time() seconds; None if it is not one."""
    try:
        return datetime.strptime(stamp, "%Y-%m-%d %H:%M:%S,%f").timestamp()
    except ValueError:
        return None


def read_worker_logs(logs: dict[Path, int]) -> dict[str, list[dict]]:
    """Per worker log (by file stem), from the byte offset given for it, the lines of the partition protocol of
    roadgrip/cloud/cluster/worker.py and spread.py, in order: {"t": time.time() s, "event": "taken" (with "partition"
    and "epoch"), "released", "releasing" (the spread rule's decision), "lost" (a partition's connection given up)
    with "partition", or "live" (the live workers' count as the spread rule saw it change) with "workers"}."""
    found = {}
    for path, offset in logs.items():
        with open(path, "rb") as f:
            f.seek(offset)
            text = f.read().decode(errors="replace")
        events = []
        for line in text.splitlines():
            stamp, _, message = line.partition(": ")
            t = _parse_time(stamp.rsplit(" ", 2)[0]) if message else None
            if t is None:
                continue
            for event, pattern in _LOG_PATTERNS:
                m = pattern.match(message)
                if m is not None:
                    events.append({"t": t, "event": event, **{k: int(v) for k, v in m.groupdict().items()}})
                    break
        found[path.stem] = events
    return found


def count_moves(logs: dict[str, list[dict]], events: dict[str, float], partitions: int, workers: int) -> dict:
    """The partition moves in the workers' log events (`read_worker_logs`), against issue 25's target.

    A partition's owners follow its epochs (each take raises it by one, across workers): a take by another worker
    than the previous one is an owner change; one by the same worker (its connection through a dead node given up,
    then registered again through another) is not. Moves are the spread rule's releases; before the worker kill they
    spread the first takes (at most partitions - ceil(partitions / workers) of them), from it on at most one per real
    change of the live workers, and the kill is the only one (the node kill and restart change no worker)."""
    takes = sorted(
        (e["partition"], e["epoch"], e["t"], worker)
        for worker, evs in logs.items()
        for e in evs
        if e["event"] == "taken"
    )
    owner_changes, retakes = [], 0
    for (p0, _, _, w0), (p1, _, t1, w1) in itertools.pairwise(takes):
        if p0 == p1:
            if w0 != w1:
                owner_changes.append(t1)
            else:
                retakes += 1
    kill = events.get("worker_kill", math.inf)
    released = sorted(e["t"] for evs in logs.values() for e in evs if e["event"] == "released")
    live = {
        worker: [n for n, _ in itertools.groupby(e["workers"] for e in evs if e["event"] == "live")]
        for worker, evs in logs.items()
    }
    before = sum(t < kill for t in released)
    after = len(released) - before
    return {
        "takes": len(takes),
        "retakes_by_the_same_worker": retakes,
        "owner_changes": len(owner_changes),
        "owner_changes_from_worker_kill": sum(t >= kill for t in owner_changes),
        "released_before_worker_kill": before,
        "released_from_worker_kill": after,
        "lost_connections": sum(e["event"] == "lost" for evs in logs.values() for e in evs),
        "live_workers_seen": live,
        "within_target": before <= partitions - -(-partitions // workers) and after <= 1,
    }


def run_failover_bench(bench: FailoverBench, data_dir: Path, progress: Progress = lambda message: None) -> dict:
    """Start the local cluster in `data_dir` (new or empty), drive the fleet through the kills, count (module
    docstring) and stop the cluster; returns the results (JSON-able)."""
    started = time.monotonic()
    cluster = LocalCluster(data_dir, nodes=3, workers=2, apis=1, partitions=bench.partitions)
    cluster.start(progress=lambda step: progress(f"starting the local cluster: {step}"))
    result: dict = {"config": asdict(bench), "cluster_start_s": round(time.monotonic() - started, 1)}
    poller = None
    try:
        progress(f"simulating {bench.vehicles} vehicles")
        network = generated_network()
        plans = plan_fleet(network, bench.vehicles, duration_s=bench.duration_s, seed=bench.seed, prefix="failover")
        samples = simulate_fleet(plans, network)
        secrets, _ = register_fleet(
            cluster.api_urls[0], cluster.admin_secret, [(p.vehicle_id, p.vehicle.name) for p in plans]
        )
        progress("vehicles connecting")
        terminals = MqttTerminals(cluster.mqtt_urls, secrets, "3.1.1")
        poller = _StoredPoller(cluster.database_url, bench.poll_s)
        poller.start()
        logs = {child.log_path: child.log_path.stat().st_size for child in cluster.workers}
        events: dict[str, float] = {}
        on_node: list[str] = []
        stop_events = threading.Event()

        def inject() -> None:
            at = time.time()
            for offset, name in (
                (bench.worker_kill_s, "worker_kill"),
                (bench.node_kill_s, "node_kill"),
                (bench.node_restart_s, "node_restart"),
            ):
                if stop_events.wait(max(0.0, at + offset - time.time())):
                    return
                progress(f"{name.replace('_', ' ')} at {offset:.0f} s")
                events[name] = time.time()
                if name == "worker_kill":
                    os.killpg(cluster.workers[0].pid, signal.SIGKILL)
                elif name == "node_kill":
                    url = cluster.mqtt_urls[bench.node]
                    on_node.extend(vid for vid, c in terminals.counts.items() if c.endpoint == url)
                    cluster.rabbit.kill(bench.node)
                else:
                    cluster.rabbit.restart(bench.node)
                    events["node_restarted"] = time.time()

        injector = threading.Thread(target=inject, name="fault-injector", daemon=True)
        result["load_average_at_drive_start"] = [round(x, 2) for x in os.getloadavg()]  # this machine's, 1/5/15 min
        drive_start = time.time()
        injector.start()
        progress(f"driving {bench.vehicles} vehicles for {bench.duration_s:.0f} s")
        drive = timeline(samples, 1.0, time.time())
        produced_until = {}  # per vehicle, the wall time of its last sample (drives end where their road does)
        for sample in drive:
            produced_until[sample["vehicle_id"]] = sample["timestamp_ms"] / 1000
        try:
            sent = replay(drive, lambda b: terminals.send(b[0]["vehicle_id"], b))
        finally:
            drive_end = time.time()
            result["load_average_at_drive_end"] = [round(x, 2) for x in os.getloadavg()]
            progress("waiting for the last PUBACKs")
            terminals.close(60.0)
            stop_events.set()
            injector.join()
        progress("waiting for the stored counts to settle")
        quiet_since, last = time.monotonic(), None
        deadline = time.monotonic() + bench.settle_timeout_s
        while time.monotonic() < deadline and time.monotonic() - quiet_since < SETTLE_QUIET_S:
            now = poller.latest()
            if now != last:
                quiet_since, last = time.monotonic(), now
            time.sleep(bench.poll_s)
        poller.stop()
        stored = poller.latest()
        worker_log = read_worker_logs(logs)
        vehicles = []
        for k, (vid, counts) in enumerate(terminals.counts.items()):
            rows = stored.get(vid, (0, 0))[0]
            killed_at = events.get("node_kill")
            drove_on = killed_at is not None and produced_until[vid] > killed_at  # its road had not ended
            resumed = _resumed(poller.polls, vid, killed_at) if vid in on_node and drove_on else None
            vehicles.append(
                {
                    "vehicle": vid,
                    "first_node": k % 3,
                    "on_killed_node": vid in on_node,
                    "drove_after_node_kill": drove_on,
                    "sent": counts.sent,
                    "pubacked": counts.acknowledged,
                    "stored": rows,
                    "lost_by_client": counts.lost,
                    "pubacked_not_stored": max(0, counts.acknowledged - rows),
                    "moves": counts.moves,
                    "longest_outage_s": round(counts.longest_outage_s, 2),
                    "longest_stall_s": round(
                        _longest_stall(poller.polls, vid, drive_start + 2.0, min(drive_end, produced_until[vid])), 2
                    ),
                    "resumed_s": None if resumed is None else round(resumed, 2),
                }
            )
        result.update(
            {
                "events_s": {name: round(t - drive_start, 2) for name, t in events.items()},
                "drive_s": round(drive_end - drive_start, 1),
                "late_batches": sent.late_batches,
                "vehicles": vehicles,
                "worker_log": {
                    worker: [{**e, "t": round(e["t"] - drive_start, 2)} for e in evs]
                    for worker, evs in worker_log.items()
                },
                "partition_moves": count_moves(worker_log, events, bench.partitions, len(cluster.workers)),
                "settled": time.monotonic() - quiet_since >= SETTLE_QUIET_S,
            }
        )
    finally:
        if poller is not None:
            poller.stop()
        progress("stopping the local cluster")
        cluster.stop()
    result["elapsed_s"] = round(time.monotonic() - started, 1)
    result["summary"] = summarize(result)
    return result


def summarize(result: dict) -> dict:
    """Totals and the issue's targets, met or not."""
    vehicles = result["vehicles"]
    total = {f: sum(v[f] for v in vehicles) for f in ("sent", "pubacked", "stored", "lost_by_client")}
    resumed = [v["resumed_s"] for v in vehicles if v["on_killed_node"] and v["drove_after_node_kill"]]
    moves = result["partition_moves"]
    return {
        **total,
        "pubacked_not_stored": sum(v["pubacked_not_stored"] for v in vehicles),
        "vehicles_on_killed_node": sum(v["on_killed_node"] for v in vehicles),
        "slowest_resume_s": None if None in resumed else max(resumed, default=None),
        "longest_stall_s": max(v["longest_stall_s"] for v in vehicles),
        "targets": {
            "resumed_within_10_s": None not in resumed and all(r <= RESUME_TARGET_S for r in resumed),
            "no_pubacked_sample_lost": all(v["pubacked_not_stored"] == 0 for v in vehicles),
            "no_sample_lost_by_client": total["lost_by_client"] == 0,
            "partition_moves_within_target": moves["within_target"],
        },
    }


def format_failover_bench(result: dict):
    """Per-vehicle rows as a rich Table."""
    from rich.table import Table

    events = ", ".join(f"{name.replace('_', ' ')} {t:.1f} s" for name, t in result["events_s"].items())
    table = Table(title=f"roadgrip bench failover: {events}")
    for column in (
        "vehicle",
        "node",
        "sent",
        "PUBACKed",
        "stored",
        "lost (client)",
        "PUBACKed not stored",
        "moves",
        "longest stall",
        "resumed after kill",
    ):
        table.add_column(column, justify="left" if column == "vehicle" else "right")
    for v in result["vehicles"]:
        resumed = "-" if not v["on_killed_node"] else ("never" if v["resumed_s"] is None else f"{v['resumed_s']:.1f} s")
        table.add_row(
            v["vehicle"],
            f"rg{v['first_node']}" + (" (killed)" if v["on_killed_node"] else ""),
            f"{v['sent']:,}",
            f"{v['pubacked']:,}",
            f"{v['stored']:,}",
            f"{v['lost_by_client']:,}",
            f"{v['pubacked_not_stored']:,}",
            str(v["moves"]),
            f"{v['longest_stall_s']:.1f} s",
            resumed,
        )
    return table
