"""Helpers of the cluster mode's tests (tests/cloud/cluster/test_worker.py, tests/cloud/cluster/test_regions.py,
tests/cloud/cluster/test_api_backend.py): a RabbitMQ cluster for a module, a node of it killed for a test and started
again after it (so that the module's tests may run in any order), `roadgrip worker` as a process of its own."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from roadgrip.cloud.transport.amqp import RabbitCluster

ROADGRIP = Path(sys.executable).parent / "roadgrip"


@contextlib.contextmanager
def running_rabbit_cluster(root: Path, vehicles: list[str], partitions: int, secret: str) -> Iterator[RabbitCluster]:
    """A 3-node RabbitMQ cluster in `root` with the partition topology and a login per vehicle, stopped after; fails
    (never skips) when RabbitMQ is not installed."""
    if not (RabbitCluster.bin_dir / "rabbitmq-server").exists():
        pytest.fail("rabbitmq-server is not installed: run `bash scripts/install_system_deps.sh`", pytrace=False)
    rabbit = RabbitCluster(root, vehicles, partitions, secret)
    try:
        rabbit.start()
        rabbit.setup()
        yield rabbit
    finally:
        rabbit.stop()


@contextlib.contextmanager
def node_killed(cluster: RabbitCluster, i: int) -> Iterator[None]:
    """Node i killed (kill -9) for the block, started again after it, even when the block fails: the module's other
    tests find the three nodes running."""
    cluster.kill(i)
    try:
        yield
    finally:
        cluster.restart(i)
        running = cluster.describe()["running_nodes"]
        assert cluster.node_name(i) in running, f"node {i} not back in the cluster: running {running}"


class WorkerProcess:
    """`roadgrip worker` in a process of its own, with the brokers in the order given, its rate limit off (the tests'
    vehicles drive faster than real time) and `env` beside it (settings as ROADGRIP_* variables)."""

    def __init__(
        self,
        cluster: RabbitCluster,
        nodes: list[int],
        database_url: str,
        log_path: Path,
        partitions: int,
        options: tuple[str, ...] = (),
        env: dict[str, str] | None = None,
    ):
        self.log_path = log_path
        brokers = [arg for i in nodes for arg in ("--broker", cluster.amqp_url(i))]
        environment = {**os.environ, "ROADGRIP_RATE_LIMIT_SAMPLES_PER_S": "0", **(env or {})}
        with open(log_path, "wb") as log:
            self.proc = subprocess.Popen(
                [
                    str(ROADGRIP),
                    "worker",
                    "--database",
                    database_url,
                    "--partitions",
                    str(partitions),
                    *brokers,
                    *options,
                ],
                stdout=log,
                stderr=subprocess.STDOUT,
                env=environment,
            )

    def log(self) -> str:
        return self.log_path.read_text()

    def wait_ready(self, timeout_s: float = 90.0) -> None:
        deadline = time.monotonic() + timeout_s
        while "worker consuming" not in self.log():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                pytest.fail(f"worker not ready:\n{self.log()[-3000:]}", pytrace=False)
            time.sleep(0.2)

    def kill(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> dict:
        """SIGTERM; the counters it logged when it stopped, which it must have ({} for a worker killed before)."""
        if self.proc.poll() == -signal.SIGKILL:
            return {}
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self.proc.wait(90)
        lines = [line for line in self.log().splitlines() if "worker stopped: " in line]
        assert lines, f"the worker did not stop cleanly:\n{self.log()[-3000:]}"
        return json.loads(lines[-1].split("worker stopped: ", 1)[1])
