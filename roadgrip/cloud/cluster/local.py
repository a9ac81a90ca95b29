"""The cluster mode on one machine (`roadgrip cluster up`, issue 17 item 5): every process of a cluster
(docs/CLUSTER.md) started on 127.0.0.1 at free ports, in one data directory, waited for until healthy, and stopped in
order.

| process | how many | started as | healthy when | its log, under the data directory |
| --- | --- | --- | --- | --- |
| RabbitMQ node | `nodes` (3) | `rabbitmq-server` (roadgrip.cloud.transport.amqp.RabbitCluster), joined into one cluster, the partition topology declared | the cluster runs every node, MQTT and management listeners open | rabbitmq/rgN/log/, rabbitmq/rgN/stdout.log |
| PostgreSQL | 1 | `pg_ctl start` (roadgrip.cloud.storage.local_postgres.LocalPostgres), database `roadgrip` | `pg_ctl start -w` returned, the database created | postgres/server.log |
| worker | `workers` | `roadgrip worker --metrics-port` (roadgrip/cloud/cluster/worker.py) | every partition queue counts its consumer (management API), its /metrics answers | logs/worker-N.log |
| API replica | `apis` | `roadgrip api` (roadgrip/cloud/cluster/api_backend.py) | `GET /v1/health` answers 200 | logs/api-N.log |

The workers and the API replicas run in sessions of their own: Ctrl-C in a terminal reaches only the process that runs
the cluster, which stops them in order (API replicas, then workers, which store what they took and checkpoint their
vehicles' states while the broker and the database still run, then the RabbitMQ nodes, then PostgreSQL), the
processes of one kind together. A child that does not stop within its grace period is killed with its whole process
group; then whatever is left of the cluster (roadgrip/cloud/cluster/reaper.py: every process whose environment
carries the cluster's tag) is killed too, so a stop ends within API_STOP_S + WORKER_STOP_S + RabbitCluster's
NODE_STOP_S + PostgreSQL's stop + REAP_GRACE_S, whatever state the processes are in. When the process that runs the
cluster is itself killed (SIGKILL included), its reaper, a process of its own session watching a pipe only the
cluster's process holds, ends every process of the cluster within REAP_GRACE_S.

Supervision (`supervise`, called about once a second by `roadgrip cluster up`): a worker or API replica that exits is
started again with the same arguments after RESTART_FIRST_S, doubling up to RESTART_MAX_S for each restart of the
same process, at most RESTART_LIMIT times (roadgrip/cloud/cluster/children.py; then it stays down, logged); a
RabbitMQ node whose server exits is started again the same way with its data (`RabbitCluster.restart`: it rejoins
the cluster and its quorum queue members catch up from the leaders). PostgreSQL, which pg_ctl detaches, is not
supervised.

Secrets, each in a file of the data directory readable by its owner only: `admin-secret` (the API's admin, which
registers vehicles) and `broker-secret` (the RabbitMQ service user `svc`, the workers' and the APIs' login). The
workers and replicas get the broker's secret in their `--broker` URLs, visible to this machine's users in the process
list: a local trial, not a deployment (README.md, "Cluster mode", says how to run the same on several machines).

No load balancer runs here: API replica k tells the vehicles it registers the MQTT listener of node k mod `nodes`
(`roadgrip api --mqtt`), and `roadgrip fleet --mqtt URL` (one per node) spreads a fleet over the nodes itself.

A cluster is started once in its data directory: its state is not meant to be started again (the nodes' ports are
chosen afresh each time); `stop()` keeps the directory, logs and databases, for a look afterwards.
"""

from __future__ import annotations

import json
import logging
import os
import secrets
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Self

import httpx

from roadgrip.cloud.cluster.children import RESTART_LIMIT, Child, Restarts, stop_children
from roadgrip.cloud.cluster.reaper import REAP_GRACE_S, TAG, reap
from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.storage.local_postgres import LocalPostgres
from roadgrip.cloud.transport.amqp import HOST, SERVICE_USER, RabbitCluster, partition_queue

log = logging.getLogger(__name__)

DATABASE = "roadgrip"
DESCRIPTION = "cluster.json"  # what runs where, written once the cluster is ready
WORKER_STOP_S = 60.0  # a worker's clean stop stores what it took and every vehicle's state
API_STOP_S = 15.0
POLL_S = 0.25


class ClusterError(RuntimeError):
    """A process of the local cluster did not start or did not become healthy (the message says which, and where its
    log is)."""


class LocalCluster:
    """`nodes` RabbitMQ nodes, PostgreSQL, `workers` workers and `apis` API replicas in `data_dir` (module docstring).

        with LocalCluster(Path("cluster-data"), workers=2, apis=2) as cluster:   # start() ... stop()
            cluster.api_urls, cluster.mqtt_urls, cluster.admin_secret

    `partitions`: the partition queues (`roadgrip worker --partitions`). `api_port`: the first replica's HTTP port,
    the next ones on the following ports (0: free ports). `config`: a settings file given to every worker and API
    replica (`--config`); their environment (ROADGRIP_*) is this process's. `data_dir` must be empty or absent."""

    def __init__(
        self,
        data_dir: Path,
        *,
        nodes: int = 3,
        workers: int = 2,
        apis: int = 2,
        partitions: int = 4,
        api_port: int = 0,
        config: Path | None = None,
        ready_timeout_s: float = 180.0,
    ):
        for name, value, low in (
            ("nodes", nodes, 1),
            ("workers", workers, 0),
            ("apis", apis, 0),
            ("partitions", partitions, 1),
            ("api_port", api_port, 0),
        ):
            if not isinstance(value, int) or value < low:
                raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
        if api_port and api_port + apis - 1 > 65535:
            raise ValueError(f"api_port {api_port} leaves no room for {apis} replicas below 65536")
        if config is not None and not Path(config).is_file():
            raise FileNotFoundError(f"config file {config} does not exist")
        self.data_dir = Path(data_dir).resolve()
        self.nodes = nodes
        self.workers_wanted = workers
        self.apis_wanted = apis
        self.partitions = partitions
        self.api_port = api_port
        self.config = Path(config).resolve() if config is not None else None
        self.ready_timeout_s = ready_timeout_s
        self.admin_secret = secrets.token_urlsafe(24)
        self.broker_secret = secrets.token_urlsafe(24)
        self.postgres: LocalPostgres | None = None
        self.rabbit: RabbitCluster | None = None
        self.database_url: str | None = None
        self.workers: list[Child] = []
        self.apis: list[Child] = []
        self.started_s: float | None = None
        self._reaper: subprocess.Popen | None = None
        self._reaper_pipe: int | None = None  # the pipe's writing end: closed when this process ends
        self._restarts: dict[str, Restarts] = {}  # by process name (module docstring, "Supervision")

    # -------------------------------------------------------------------------------------------- where things are
    @property
    def logs_dir(self) -> Path:
        return self.data_dir / "logs"

    @property
    def _postmaster_pid(self) -> Path:
        return self.data_dir / "postgres" / "data" / "postmaster.pid"

    @property
    def admin_secret_file(self) -> Path:
        return self.data_dir / "admin-secret"

    @property
    def mqtt_urls(self) -> list[str]:
        return [f"mqtt://{HOST}:{port}" for port in self.rabbit.mqtt_ports]

    @property
    def amqp_urls(self) -> list[str]:
        """The service user's AMQP URL of each node, secret included."""
        return [self.rabbit.amqp_url(i) for i in range(self.nodes)]

    @property
    def management_urls(self) -> list[str]:
        return [f"http://{HOST}:{port}" for port in self.rabbit.management_ports]

    @property
    def api_urls(self) -> list[str]:
        return [child.url for child in self.apis]

    # --------------------------------------------------------------------------------------------- start and stop
    def start(self, progress: Callable[[str], None] | None = None) -> None:
        """Start everything and wait until each is healthy (`progress` is told each step); on any failure, or an
        interrupt, stop what was started and raise."""
        say = progress or (lambda message: None)
        started = time.monotonic()
        self._make_data_dir()
        try:
            self._start_reaper()
            say("PostgreSQL")
            self._start_postgres()
            say(f"RabbitMQ: {self.nodes} node(s) joined into one cluster (the slowest step)")
            self._start_rabbit()
            if self.workers_wanted:
                say(f"{self.workers_wanted} worker(s)")
                self._start_workers()
            if self.apis_wanted:
                say(f"{self.apis_wanted} API replica(s)")
                self._start_apis()
        except BaseException:
            self.stop()
            raise
        self.started_s = time.monotonic() - started
        (self.data_dir / DESCRIPTION).write_text(json.dumps(self.describe(), indent=1) + "\n")
        log.info("local cluster ready in %.0f s: %s", self.started_s, self.data_dir / DESCRIPTION)

    def stop(self) -> None:
        """Stop everything started, in order (module docstring), each step even when an earlier one failed, then
        kill whatever process of the cluster is left. Idempotent; the data directory is kept."""
        try:
            try:
                try:
                    stop_children(list(reversed(self.apis)), API_STOP_S)
                finally:
                    stop_children(list(reversed(self.workers)), WORKER_STOP_S)
            finally:
                if self.rabbit is not None:
                    self.rabbit.stop()
        finally:
            try:
                pg = self.postgres
                if pg is not None and pg.root is not None and (pg.root / "data" / "postmaster.pid").exists():
                    pg.stop()
            finally:
                self._stop_reaper()

    def _start_reaper(self) -> None:
        """The cluster's reaper (roadgrip/cloud/cluster/reaper.py), and the tag in this process's environment, which
        every process started from now on inherits."""
        os.environ[TAG] = str(self.data_dir)
        read_end, self._reaper_pipe = os.pipe()
        try:
            self._reaper = subprocess.Popen(
                [sys.executable, "-m", "roadgrip.cloud.cluster.reaper", str(self.data_dir), str(self._postmaster_pid)],
                stdin=read_end,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
                start_new_session=True,  # neither Ctrl-C nor a kill of this process group reaches it
            )
        finally:
            os.close(read_end)

    def _stop_reaper(self) -> None:
        """Kill what is left of the cluster, then let the reaper go (it finds nothing more) and drop the tag."""
        if self._reaper_pipe is None:
            return
        left = reap(str(self.data_dir), REAP_GRACE_S, frozenset({os.getpid()}), (self._postmaster_pid,))
        if left:
            log.warning("processes of the cluster left after its stop, killed: %s", sorted(left))
        os.close(self._reaper_pipe)
        self._reaper_pipe = None
        if self._reaper is not None:
            try:
                self._reaper.wait(REAP_GRACE_S)
            except subprocess.TimeoutExpired:
                self._reaper.kill()
                self._reaper.wait()
        if os.environ.get(TAG) == str(self.data_dir):
            del os.environ[TAG]

    def __enter__(self) -> Self:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def exited(self) -> list[Child]:
        """Workers and API replicas that have ended on their own (the others still run)."""
        return [child for child in (*self.workers, *self.apis) if child.returncode is not None]

    def nodes_down(self) -> list[int]:
        """RabbitMQ nodes whose server process has ended."""
        return [i for i, proc in enumerate(self.rabbit.procs) if proc is not None and proc.poll() is not None]

    def supervise(self, now: float) -> list[str]:
        """Start again the workers, API replicas and RabbitMQ nodes that exited, when their restart is due (module
        docstring, "Supervision"); `now`: monotonic s. Returns what it found and did, a line each (also logged)."""
        said = []
        down = [(c.name, c) for c in self.exited()] + [(f"RabbitMQ node {i}", i) for i in self.nodes_down()]
        for name, what in down:
            restarts = self._restarts.setdefault(name, Restarts())
            if restarts.due is None:
                status = what.returncode if isinstance(what, Child) else self.rabbit.procs[what].returncode
                delay = restarts.schedule(now)
                if delay is None:
                    said.append(f"{name} exited (status {status}); restarted {restarts.count} times already: left down")
                    restarts.due = float("inf")
                else:
                    said.append(
                        f"{name} exited (status {status}); restart {restarts.count + 1} of {RESTART_LIMIT} in "
                        f"{delay:.0f} s"
                    )
            elif now >= restarts.due:
                restarts.count += 1
                restarts.due = None
                try:
                    if isinstance(what, Child):
                        what.start()
                        said.append(f"{name} started again (pid {what.pid})")
                    else:
                        self.rabbit.restart(what)
                        said.append(f"{name} started again (pid {self.rabbit.pid(what)})")
                except (OSError, subprocess.SubprocessError, TimeoutError) as exc:
                    said.append(f"{name} did not start again: {exc}")  # still down: found so at the next call
                    continue
                (self.data_dir / DESCRIPTION).write_text(json.dumps(self.describe(), indent=1) + "\n")
        for line in said:
            log.warning("%s", line)
        return said

    def _make_data_dir(self) -> None:
        if self.data_dir.exists() and any(self.data_dir.iterdir()):
            raise FileExistsError(
                f"data directory {self.data_dir} is not empty: give a new or empty one (a local "
                "cluster is started once in its directory)"
            )
        self.data_dir.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:  # PostgreSQL runs as the user postgres, which must reach postgres/ through it
            self.data_dir.chmod(self.data_dir.stat().st_mode | 0o011)
        self.logs_dir.mkdir()
        for path, secret in (
            (self.admin_secret_file, self.admin_secret),
            (self.data_dir / "broker-secret", self.broker_secret),
        ):
            path.touch(mode=0o600)
            path.write_text(secret + "\n")

    def _start_postgres(self) -> None:
        self.postgres = LocalPostgres(root=self.data_dir / "postgres")
        self.postgres.start()
        self.database_url = self.postgres.create_database(DATABASE)

    def _start_rabbit(self) -> None:
        root = self.data_dir / "rabbitmq"
        root.mkdir()
        self.rabbit = RabbitCluster(root, [], self.partitions, self.broker_secret, self.nodes)
        self.rabbit.start()
        self.rabbit.setup()
        running = self.rabbit.describe()["running_nodes"]
        if len(running) != self.nodes:
            raise ClusterError(f"RabbitMQ runs {len(running)} of {self.nodes} nodes ({running}): see {root}/rg*/log")

    def _child_env(self) -> dict[str, str]:
        return {**os.environ, "ROADGRIP_ADMIN_SECRET": self.admin_secret}

    def _common_args(self) -> list[str]:
        return ["--config", str(self.config)] if self.config is not None else []

    def _start_workers(self) -> None:
        for k in range(self.workers_wanted):
            brokers = self.amqp_urls[k % self.nodes :] + self.amqp_urls[: k % self.nodes]  # spread their connections
            port = free_port()
            args = [
                "worker",
                "--database",
                self.database_url,
                "--partitions",
                str(self.partitions),
                *[arg for url in brokers for arg in ("--broker", url)],
                "--metrics-port",
                str(port),
                *self._common_args(),
            ]
            child = Child(
                f"worker {k}",
                args,
                self.logs_dir / f"worker-{k}.log",
                self._child_env(),
                url=f"http://{HOST}:{port}/metrics",
            )
            self.workers.append(child)
            child.start()
        self._wait(
            "the workers' consumers on every partition",
            self.workers,
            lambda: self._workers_registered() and all(self._answers(c.url) for c in self.workers),
        )

    def _workers_registered(self) -> bool:
        """Every partition queue counts a consumer of each worker, the active one and the waiting ones (the
        management API's count: AMQP's passive declare counts the single active consumer only)."""
        auth = (SERVICE_USER, self.broker_secret)
        try:
            counts = [
                httpx.get(f"{self.management_urls[0]}/api/queues/%2F/{partition_queue(p)}", auth=auth, timeout=5.0)
                .json()
                .get("consumers", 0)
                for p in range(self.partitions)
            ]
        except (httpx.HTTPError, ValueError):
            return False
        return min(counts) >= len(self.workers)

    def _start_apis(self) -> None:
        for k in range(self.apis_wanted):
            port = self.api_port + k if self.api_port else free_port()
            args = [
                "api",
                "--host",
                HOST,
                "--port",
                str(port),
                "--database",
                self.database_url,
                *[arg for url in self.amqp_urls for arg in ("--broker", url)],
                *[arg for url in self.management_urls for arg in ("--management", url)],
                "--mqtt",
                self.mqtt_urls[k % self.nodes],
                *self._common_args(),
            ]
            child = Child(
                f"api {k}", args, self.logs_dir / f"api-{k}.log", self._child_env(), url=f"http://{HOST}:{port}"
            )
            self.apis.append(child)
            child.start()
        self._wait(
            "the API replicas' health", self.apis, lambda: all(self._answers(f"{c.url}/v1/health") for c in self.apis)
        )

    def _answers(self, url: str) -> bool:
        """`url` answers 200 to the admin."""
        try:
            return httpx.get(url, auth=("admin", self.admin_secret), timeout=5.0).status_code == 200
        except httpx.HTTPError:
            return False

    def _wait(self, what: str, children: list[Child], healthy: Callable[[], bool]) -> None:
        deadline = time.monotonic() + self.ready_timeout_s
        while True:
            for child in children:
                if child.returncode is not None:
                    raise ClusterError(
                        f"{child.name} exited with status {child.returncode} while starting; its log "
                        f"({child.log_path}) ends:\n{child.log_tail()}"
                    )
            if healthy():
                return
            if time.monotonic() > deadline:
                raise ClusterError(f"{what} not ready within {self.ready_timeout_s:.0f} s; logs in {self.logs_dir}")
            time.sleep(POLL_S)

    # ------------------------------------------------------------------------------------------------ what runs
    def describe(self) -> dict:
        """What runs where (no secret in it: the files that hold them)."""
        rabbit_root = self.data_dir / "rabbitmq"
        return {
            "data_dir": str(self.data_dir),
            "admin_secret_file": str(self.admin_secret_file),
            "broker_secret_file": str(self.data_dir / "broker-secret"),
            "partitions": self.partitions,
            "postgres": {
                "url": self.database_url,
                "pid": self.postgres_pid(),
                "log": str(self.postgres.root / "server.log"),
            },
            "rabbitmq": [
                {
                    "node": self.rabbit.node_name(i),
                    "pid": self.rabbit.pid(i),
                    "amqp": f"amqp://{SERVICE_USER}@{HOST}:{self.rabbit.amqp_ports[i]}/%2F",
                    "mqtt": self.mqtt_urls[i],
                    "management": self.management_urls[i],
                    "log": str(rabbit_root / f"rg{i}" / "log"),
                }
                for i in range(self.nodes)
            ],
            "workers": [{"name": c.name, "pid": c.pid, "metrics": c.url, "log": str(c.log_path)} for c in self.workers],
            "apis": [{"name": c.name, "pid": c.pid, "url": c.url, "log": str(c.log_path)} for c in self.apis],
            "fleet_command": self.fleet_command(),
        }

    def postgres_pid(self) -> int | None:
        """The PostgreSQL server's process (its postmaster), while it runs."""
        pid_file = self.postgres.root / "data" / "postmaster.pid" if self.postgres and self.postgres.root else None
        return int(pid_file.read_text().split()[0]) if pid_file is not None and pid_file.exists() else None

    def fleet_command(self, vehicles: int = 10) -> str | None:
        """A `roadgrip fleet` that drives against this cluster: registered through the first API replica, its
        telemetry over MQTT 3.1.1 spread over the nodes, read back through the last replica."""
        if not self.apis:
            return None
        nodes = " ".join(f"--mqtt {url}" for url in self.mqtt_urls)
        return (
            f"roadgrip fleet --url {self.api_urls[0]} --admin-secret-file {self.admin_secret_file} "
            f"--vehicles {vehicles} {nodes} --mqtt-protocol 3.1.1 --read-url {self.api_urls[-1]}"
        )
