"""The local cluster (roadgrip/cloud/cluster/local.py, `roadgrip cluster up`) against real servers: 3 RabbitMQ nodes,
PostgreSQL, `roadgrip worker` and `roadgrip api` processes on 127.0.0.1. A fleet registers through one API replica,
sends over MQTT to the nodes and reads its estimates back through the other replica; when the cluster stops, no
process it started is left (every process below the one that ran it, and the PostgreSQL server, which pg_ctl detaches
from it). Each test starts its own cluster (about 60-90 s on 2 cores)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import psycopg
import pytest
from sqlalchemy.engine import make_url
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.cloud.cluster.local import DESCRIPTION, LocalCluster
from roadgrip.cloud.cluster.reaper import tagged
from roadgrip.cloud.transport.amqp import SERVICE_USER, RabbitCluster, partition_queue

pytestmark = [pytest.mark.cluster, pytest.mark.timeout(900)]  # needs a local RabbitMQ cluster
VEHICLES = 3
SAMPLES_PER_VEHICLE = 200  # 20 s of driving at 10 Hz
runner = CliRunner()


@pytest.fixture
def data_dir(monkeypatch):
    """A new folder under the system's temporary directory (pytest's tmp_path is private to root, and PostgreSQL runs as
    the user postgres there), removed after the test; vehicles at 20x real time are no abuse here."""
    if not (RabbitCluster.bin_dir / "rabbitmq-server").exists():
        pytest.fail("rabbitmq-server is not installed: run `bash scripts/install_system_deps.sh`", pytrace=False)
    monkeypatch.setenv("ROADGRIP_RATE_LIMIT_SAMPLES_PER_S", "0")
    path = Path(tempfile.mkdtemp(prefix="roadgrip-cluster-test-"))
    yield path
    shutil.rmtree(path, ignore_errors=True)


def processes() -> dict[int, tuple[int, int]]:
    """pid -> (parent pid, start time in clock ticks) of every process that runs, from /proc (a zombie has ended:
    only its exit status waits for its parent, or for init when it was an orphan)."""
    table = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue  # ended meanwhile
        if fields[0] != "Z":
            table[int(entry.name)] = (int(fields[1]), int(fields[19]))
    return table


def below(*roots: int) -> set[tuple[int, int]]:
    """(pid, start time) of the roots and of every process below them."""
    table = processes()
    children: dict[int, list[int]] = {}
    for pid, (parent, _) in table.items():
        children.setdefault(parent, []).append(pid)
    found, todo = set(), [r for r in roots if r in table]
    while todo:
        pid = todo.pop()
        found.add((pid, table[pid][1]))
        todo += children.get(pid, [])
    return found


def left(started: set[tuple[int, int]]) -> set[tuple[int, int]]:
    """Those of `started` still there (the same pid with the same start time: not a reused pid)."""
    table = processes()
    return {(pid, start) for pid, start in started if pid in table and table[pid][1] == start}


def command_lines(pids: set[tuple[int, int]]) -> list[str]:
    lines = []
    for pid, _ in pids:
        try:
            lines.append(f"{pid}: " + (Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()[:200]))
        except OSError:
            lines.append(f"{pid}: ended")
    return lines


def test_counts_and_a_used_data_directory_are_refused_before_anything_starts(tmp_path):
    for bad in ({"nodes": 0}, {"workers": -1}, {"apis": 1.5}, {"partitions": 0}, {"api_port": -2}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            LocalCluster(tmp_path / "new", **bad)
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "something").write_text("")
    with pytest.raises(FileExistsError, match="not empty"):
        LocalCluster(tmp_path / "used").start()
    assert not (tmp_path / "used" / "logs").exists()


def test_an_interrupt_while_starting_stops_what_was_started(data_dir):
    """Ctrl-C after PostgreSQL and RabbitMQ are up, as the workers are about to start (the progress callback runs
    before each step): start() stops both and raises the interrupt; nothing is left."""
    cluster = LocalCluster(data_dir, nodes=1, workers=1, apis=0, partitions=1)
    seen: dict[str, set[tuple[int, int]]] = {}
    before = below(os.getpid())  # this process and what it ran before (multiprocessing's resource tracker)

    def progress(step: str) -> None:
        if "worker" in step:
            seen["started"] = below(os.getpid(), cluster.postgres_pid()) - before
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        cluster.start(progress)
    assert not cluster.workers and not (data_dir / DESCRIPTION).exists()
    assert len(seen["started"]) >= 3  # PostgreSQL's, the node's server, epmd
    remaining = left(seen["started"])
    assert not remaining, "left running:\n" + "\n".join(command_lines(remaining))


def test_a_fleet_drives_against_the_local_cluster_and_nothing_is_left_after_it_stops(data_dir):
    cluster = LocalCluster(data_dir, workers=2, apis=2, partitions=4)
    before = below(os.getpid())  # this process and what it ran before (multiprocessing's resource tracker)
    try:
        cluster.start()
        described = json.loads((data_dir / DESCRIPTION).read_text())
        assert len(described["rabbitmq"]) == 3 and len(described["workers"]) == 2 and len(described["apis"]) == 2
        started = below(os.getpid(), described["postgres"]["pid"]) - before
        for node in described["rabbitmq"]:
            assert node["pid"] in {pid for pid, _ in started}  # the nodes' servers are the cluster's children

        register, read = cluster.api_urls  # one replica registers, the other reads
        result = runner.invoke(
            app,
            [
                "fleet",
                "--url",
                register,
                "--admin-secret-file",
                str(cluster.admin_secret_file),
                "--vehicles",
                str(VEHICLES),
                "--speed",
                "20",
                "--duration",
                "20",
                *[arg for url in cluster.mqtt_urls for arg in ("--mqtt", url)],
                "--read-url",
                read,
                "--prefix",
                "lc",
            ],
        )
        said = " ".join(result.output.split())
        assert result.exit_code == 0, result.output
        # "auto" found that RabbitMQ 3.10 does not take MQTT 5, and every sample got its PUBACK
        n = VEHICLES * SAMPLES_PER_VEHICLE
        assert f"over MQTT 3.1.1 to 3 broker(s): sent {n:,} samples, PUBACKed {n:,}, lost 0 " in said, said
        assert f"of {VEHICLES} of {VEHICLES} vehicles" in said, said

        url = make_url(cluster.database_url).set(drivername="postgresql").render_as_string(hide_password=False)
        with psycopg.connect(url) as conn:
            telemetry = dict(conn.execute("SELECT vehicle_id, count(*) FROM telemetry GROUP BY vehicle_id").fetchall())
            estimates = dict(conn.execute("SELECT vehicle_id, count(*) FROM estimates GROUP BY vehicle_id").fetchall())
        vehicles = [f"lc-{k:03d}" for k in range(VEHICLES)]
        assert telemetry == {v: SAMPLES_PER_VEHICLE for v in vehicles}  # each PUBACKed sample stored once
        for v in vehicles:
            answer = httpx.get(
                f"{read}/v1/vehicles/{v}/estimates",
                params={"limit": 100_000},
                auth=("admin", cluster.admin_secret),
                timeout=30,
            )
            assert answer.status_code == 200 and len(answer.json()["estimates"]) == estimates[v] > 0
        # the map: the workers' region owners save its cells about once a second; the replica reads them
        deadline = time.monotonic() + 30
        while not httpx.get(f"{read}/v1/map", auth=("admin", cluster.admin_secret), timeout=30).json()["features"]:
            assert time.monotonic() < deadline, "no map cell readable through the replica"
            time.sleep(1.0)
    finally:
        cluster.stop()
    for child in (*cluster.workers, *cluster.apis):  # on SIGTERM, within the grace period: not killed
        assert child.returncode in (0, 128 + signal.SIGTERM), f"{child.name} did not stop cleanly:\n{child.log_tail()}"
    remaining = left(started)
    assert not remaining, "left running:\n" + "\n".join(command_lines(remaining))


def cluster_up(data_dir: Path, out: Path, *options: str, sigint_ignored: bool = False) -> subprocess.Popen:
    """`roadgrip cluster up` in a process group of its own, as a terminal's job, its output in `out`; with
    `sigint_ignored`, started with SIGINT ignored, as a shell script's background job starts it (and the test suite
    run that way: the cause of issue 25's flake)."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN) if sigint_ignored else None
    try:
        with open(out, "wb") as log:
            return subprocess.Popen(
                [sys.executable, "-m", "roadgrip", "cluster", "up", "--data-dir", str(data_dir), *options],
                stdout=log,
                stderr=subprocess.STDOUT,
                env={**os.environ, "COLUMNS": "200"},
                start_new_session=True,
            )
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def wait_for_text(proc: subprocess.Popen, out: Path, text: str, timeout_s: float = 300) -> None:
    deadline = time.monotonic() + timeout_s
    while text not in out.read_text():
        assert proc.poll() is None and time.monotonic() < deadline, out.read_text()
        time.sleep(0.5)


@pytest.mark.parametrize("stop", ["sigterm", "ctrl-c"])
def test_roadgrip_cluster_up_runs_until_stopped_then_stops_everything(data_dir, stop):
    """SIGTERM to the command (a service manager), or SIGINT to its whole process group (Ctrl-C in a terminal
    reaches every process of the foreground job: the ones the command runs in sessions of their own do not get it),
    the command started with SIGINT ignored (a background job of a script, as the full suite may be)."""
    out = data_dir.parent / f"{data_dir.name}.out"
    options = ["--nodes", "2", "--workers", "1", "--apis", "1", "--partitions", "2"]
    proc = cluster_up(data_dir, out, *options, sigint_ignored=stop == "ctrl-c")
    try:
        wait_for_text(proc, out, "local cluster ready")
        described = json.loads((data_dir / DESCRIPTION).read_text())
        assert len(described["rabbitmq"]) == 2
        started = below(proc.pid, described["postgres"]["pid"], *[node["pid"] for node in described["rabbitmq"]])
        said = " ".join(out.read_text().split())
        assert described["apis"][0]["url"] in said and str(data_dir / "admin-secret") in said
        assert described["fleet_command"] in said
        assert len(started) > 7  # the command, 2 nodes (and their helpers), PostgreSQL's, a worker, an API
        if stop == "sigterm":
            proc.send_signal(signal.SIGTERM)
        else:
            os.killpg(proc.pid, signal.SIGINT)
        assert proc.wait(180) == 0, out.read_text()
        assert "local cluster stopped" in out.read_text()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        out.unlink(missing_ok=True)
    remaining = left(started) | {(pid, 0) for pid in tagged(str(data_dir))}
    assert not remaining, "left running:\n" + "\n".join(command_lines(remaining))


def test_cluster_up_restarts_a_killed_worker_and_node_and_when_killed_itself_leaves_nothing_behind(data_dir):
    """kill -9 of the worker: started again (the same metrics port answers from a new pid); kill -9 of the RabbitMQ
    node's server: started again with its data (a new pid; the partition queue is back and the worker consumes it
    again); then kill -9 of `cluster up` itself: its reaper ends every process of the cluster, PostgreSQL's
    included, within 30 s."""
    out = data_dir.parent / f"{data_dir.name}.out"
    proc = cluster_up(data_dir, out, "--nodes", "1", "--workers", "1", "--apis", "0", "--partitions", "1")
    try:
        wait_for_text(proc, out, "local cluster ready")
        described = json.loads((data_dir / DESCRIPTION).read_text())
        started = below(proc.pid, described["postgres"]["pid"], described["rabbitmq"][0]["pid"])
        worker = described["workers"][0]
        os.kill(worker["pid"], signal.SIGKILL)
        wait_for_text(proc, out, "worker 0 started again", timeout_s=60)
        restarted = json.loads((data_dir / DESCRIPTION).read_text())["workers"][0]
        assert restarted["pid"] != worker["pid"]
        deadline = time.monotonic() + 90
        while not _answers(restarted["metrics"]):
            assert time.monotonic() < deadline, (data_dir / "logs" / "worker-0.log").read_text()[-3000:]
            time.sleep(0.5)

        node = described["rabbitmq"][0]
        os.kill(node["pid"], signal.SIGKILL)
        wait_for_text(proc, out, "RabbitMQ node 0 started again", timeout_s=240)
        assert json.loads((data_dir / DESCRIPTION).read_text())["rabbitmq"][0]["pid"] != node["pid"]
        queue = f"{node['management']}/api/queues/%2F/{partition_queue(0)}"
        auth = (SERVICE_USER, (data_dir / "broker-secret").read_text().strip())
        deadline = time.monotonic() + 90
        while _consumers(queue, auth) < 1:
            assert time.monotonic() < deadline, (data_dir / "logs" / "worker-0.log").read_text()[-3000:]
            time.sleep(0.5)

        started |= below(proc.pid)
        proc.kill()
        proc.wait()
        killed = time.monotonic()
        while remaining := left(started) | {(pid, 0) for pid in tagged(str(data_dir))}:
            assert time.monotonic() - killed < 30, "left running:\n" + "\n".join(command_lines(remaining))
            time.sleep(0.5)
        print(
            f"\nkill -9 of cluster up: none of its {len(started)} processes left {time.monotonic() - killed:.1f} s after"
        )
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        out.unlink(missing_ok=True)


def _consumers(queue_url: str, auth: tuple[str, str]) -> int:
    """The queue's consumers as the management API counts them (0 while it does not answer)."""
    try:
        return httpx.get(queue_url, auth=auth, timeout=5.0).json().get("consumers", 0)
    except (httpx.HTTPError, ValueError):
        return 0


def _answers(url: str) -> bool:
    try:
        return httpx.get(url, timeout=5.0).status_code == 200
    except httpx.HTTPError:
        return False
