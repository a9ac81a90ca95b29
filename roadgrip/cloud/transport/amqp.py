"""RabbitMQ in cluster mode (issue 17; the choice and its measurements: docs/CLUSTER.md): the partition topology that
carries vehicles' MQTT telemetry to the workers (roadgrip/cloud/cluster/worker.py), and a local 3-node cluster on 127.0.0.1
for trials and tests (`RabbitCluster`, used by results/trials/cluster/broker_trial.py and tests/cloud/cluster/test_worker.py).

The topology (`topology`, declared idempotently by `declare_topology`):

| name | kind | what it does |
| --- | --- | --- |
| amq.topic | topic exchange | where the MQTT plugin publishes (`mqtt.exchange`): the topic with '/' as '.' (and '.' as '/') |
| amq.topic -> rg.telemetry | exchange-to-exchange binding, key `roadgrip.v1.vehicles.*.telemetry` | forwards telemetry only |
| rg.telemetry | x-consistent-hash exchange | spreads by a hash of the routing key, hence of the vehicle id |
| rg.telemetry.p0 .. pN-1 | quorum queues, x-single-active-consumer | one partition each, weight 1: every message of a vehicle in one queue, in order; one consumer of a queue active at a time |
| rg.estimates | x-consistent-hash exchange | the second keyed stage (issue 17 item 3): workers publish stored estimates and station evidence there, routing key the region (H3 parent cell), spread by a hash of it |
| rg.estimates.r0 .. rM-1 | quorum queues, x-single-active-consumer | one region queue each, weight 1: every message of a region in one queue; its active consumer owns those regions' map and warnings (roadgrip/cloud/cluster/regions.py) |
| amq.topic -> rg.edge | bindings, keys `roadgrip.v1.vehicles.*.observations` and `roadgrip.v1.vehicles.*.heartbeat` | edge vehicles' MQTT messages (CONTRACTS 3.7) |
| rg.edge | quorum queue, x-single-active-consumer | every edge vehicle's observations and heartbeats, in order; its active consumer stores them and hands their passes to the region stage (roadgrip/cloud/cluster/edge.py) |

N and M are fixed when the queues are first declared: another N re-hashes part of the vehicles onto other queues,
another M part of the regions (do it only with the workers drained). Declaring a queue that exists with other
arguments fails (PRECONDITION_FAILED).
"""

from __future__ import annotations

import base64
import hashlib
import json
import os
import secrets
import signal
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from roadgrip.cloud.localhost import free_ports, wait_port

HOST = "127.0.0.1"
SERVICE_USER = "svc"  # RabbitCluster's administrator: the workers' login
MQTT_EXCHANGE = "amq.topic"
TELEMETRY_EXCHANGE = "rg.telemetry"
TELEMETRY_BINDING = "roadgrip.v1.vehicles.*.telemetry"
ESTIMATES_EXCHANGE = "rg.estimates"
EDGE_QUEUE = "rg.edge"
EDGE_BINDINGS = ("roadgrip.v1.vehicles.*.observations", "roadgrip.v1.vehicles.*.heartbeat")
REGION_QUEUES = 4  # M, the region queues, unless the settings say otherwise (Settings.region_queues)
NODE_STOP_S = 30.0  # RabbitCluster.stop: a node's clean stop, before SIGKILL
KILLED_WAIT_S = 5.0  # a process signalled at the end of a stop is waited for this long


def partition_queue(partition: int) -> str:
    return f"{TELEMETRY_EXCHANGE}.p{partition}"


def region_queue(index: int) -> str:
    return f"{ESTIMATES_EXCHANGE}.r{index}"


def mqtt_routing_key(topic: str) -> str:
    """The routing key in amq.topic of an MQTT topic (the MQTT plugin swaps '/' and '.'), and back."""
    return topic.translate(str.maketrans("./", "/."))


def _ordered_queue(name: str) -> dict:
    """A quorum queue with single-active-consumer: replicated, delivered in order to one consumer at a time."""
    return {
        "name": name,
        "vhost": "/",
        "durable": True,
        "auto_delete": False,
        "arguments": {"x-queue-type": "quorum", "x-single-active-consumer": True},
    }


def _keyed_queues(exchange: str, names: list[str]) -> tuple[list[dict], list[dict], dict]:
    """Quorum queues with single-active-consumer behind a consistent-hash exchange, weight 1 each."""
    queues = [_ordered_queue(name) for name in names]
    bindings = [
        {
            "source": exchange,
            "vhost": "/",
            "destination": name,
            "destination_type": "queue",
            "routing_key": "1",
            "arguments": {},
        }
        for name in names
    ]  # the binding key is the queue's weight
    return (
        queues,
        bindings,
        {
            "name": exchange,
            "vhost": "/",
            "type": "x-consistent-hash",
            "durable": True,
            "auto_delete": False,
            "internal": False,
            "arguments": {},
        },
    )


def topology(partitions: int, region_queues: int = REGION_QUEUES) -> dict:
    """The exchanges, queues and bindings of `partitions` partitions and `region_queues` region queues, as
    RabbitMQ's definitions (the keys of `rabbitmqctl import_definitions`)."""
    if not isinstance(partitions, int) or partitions < 1:
        raise ValueError(f"partitions must be a positive integer, got {partitions!r}")
    if isinstance(region_queues, bool) or not isinstance(region_queues, int) or region_queues < 1:
        raise ValueError(f"region_queues must be a positive integer, got {region_queues!r}")
    queues, bindings, telemetry = _keyed_queues(TELEMETRY_EXCHANGE, [partition_queue(p) for p in range(partitions)])
    forward = {
        "source": MQTT_EXCHANGE,
        "vhost": "/",
        "destination": TELEMETRY_EXCHANGE,
        "destination_type": "exchange",
        "routing_key": TELEMETRY_BINDING,
        "arguments": {},
    }
    region_qs, region_bindings, estimates = _keyed_queues(
        ESTIMATES_EXCHANGE, [region_queue(r) for r in range(region_queues)]
    )
    edge = [
        {
            "source": MQTT_EXCHANGE,
            "vhost": "/",
            "destination": EDGE_QUEUE,
            "destination_type": "queue",
            "routing_key": key,
            "arguments": {},
        }
        for key in EDGE_BINDINGS
    ]
    return {
        "exchanges": [telemetry, estimates],
        "queues": queues + region_qs + [_ordered_queue(EDGE_QUEUE)],
        "bindings": [forward, *bindings, *region_bindings, *edge],
    }


def declare_topology(channel, partitions: int, region_queues: int = REGION_QUEUES) -> None:
    """Declare `topology(partitions, region_queues)` on a pika channel: a no-op where it exists as declared."""
    t = topology(partitions, region_queues)
    for e in t["exchanges"]:
        channel.exchange_declare(
            e["name"],
            e["type"],
            durable=e["durable"],
            auto_delete=e["auto_delete"],
            internal=e["internal"],
            arguments=e["arguments"],
        )
    for q in t["queues"]:
        channel.queue_declare(q["name"], durable=q["durable"], auto_delete=q["auto_delete"], arguments=q["arguments"])
    for b in t["bindings"]:
        if b["destination_type"] == "exchange":
            channel.exchange_bind(b["destination"], b["source"], routing_key=b["routing_key"], arguments=b["arguments"])
        else:
            channel.queue_bind(b["destination"], b["source"], routing_key=b["routing_key"], arguments=b["arguments"])


def rabbit_password_hash(password: str) -> str:
    salt = secrets.token_bytes(4)
    return base64.b64encode(salt + hashlib.sha256(salt + password.encode()).digest()).decode()


# The plugins every node runs. Management last: a joining node starts it after the join, since with its agent running
# `rabbitmqctl stop_app` (which the join needs) takes 5.4 s instead of 0.4 s (RabbitMQ 3.10.8, measured 2026-12-06):
# a three-node start 26.5 -> 18.3 s.
PLUGINS = ("rabbitmq_mqtt", "rabbitmq_consistent_hash_exchange", "rabbitmq_management")


class RabbitCluster:
    """`nodes` RabbitMQ nodes (three by default: rg0..rg2@localhost) on their own epmd, joined with `rabbitmqctl join_cluster`, plugins
    rabbitmq_mqtt, rabbitmq_consistent_hash_exchange and rabbitmq_management (the HTTP API through which `roadgrip
    api` manages vehicles' broker users: roadgrip/cloud/transport/rabbit_users.py; a listener per node on 127.0.0.1,
    `management_url`). MQTT publishes land in amq.topic (routing key: the topic with
    '/' as '.'); an exchange-to-exchange binding forwards telemetry to a consistent-hash exchange that spreads it, by a
    hash of the routing key (hence of the vehicle id), over N quorum queues with single-active-consumer; edge vehicles'
    observations and heartbeats go to the queue rg.edge. A vehicle may publish only its own telemetry, observations
    and heartbeat topics (topic permissions on amq.topic)."""

    name = "rabbitmq"
    bin_dir = Path("/usr/lib/rabbitmq/bin")

    def __init__(self, root: Path, vehicles: list[str], partitions: int, secret: str, nodes: int = 3):
        if not isinstance(nodes, int) or nodes < 1:
            raise ValueError(f"nodes must be a positive integer, got {nodes!r}")
        self.root, self.vehicles, self.partitions, self.secret = root, vehicles, partitions, secret
        self.nodes = nodes
        ports = free_ports(4 * nodes + 1)
        self.amqp_ports, self.dist_ports = ports[0:nodes], ports[nodes : 2 * nodes]
        self.mqtt_ports, self.management_ports = ports[2 * nodes : 3 * nodes], ports[3 * nodes : 4 * nodes]
        self.epmd_port = ports[4 * nodes]
        self.procs: list[subprocess.Popen | None] = [None] * nodes
        self.epmd: subprocess.Popen | None = None
        self.home = root / "home"

    def node_name(self, i: int) -> str:
        return f"rg{i}@localhost"

    def env(self, i: int) -> dict[str, str]:
        base = self.root / f"rg{i}"
        env_file = self.root / "rabbitmq-env.conf"
        return {
            **os.environ,
            "HOME": str(self.home),
            "ERL_EPMD_PORT": str(self.epmd_port),
            "RABBITMQ_CONF_ENV_FILE": str(env_file),
            "RABBITMQ_NODENAME": self.node_name(i),
            "RABBITMQ_NODE_IP_ADDRESS": HOST,
            "RABBITMQ_NODE_PORT": str(self.amqp_ports[i]),
            "RABBITMQ_DIST_PORT": str(self.dist_ports[i]),
            "RABBITMQ_MNESIA_BASE": str(base / "mnesia"),
            "RABBITMQ_LOG_BASE": str(base / "log"),
            "RABBITMQ_CONFIG_FILE": str(base / "rabbitmq.conf"),
            "RABBITMQ_ENABLED_PLUGINS_FILE": str(base / "enabled_plugins"),
            "RABBITMQ_PID_FILE": str(base / "pid"),
        }

    def ctl(self, i: int, *args: str, timeout_s: float = 120, tool: str = "rabbitmqctl") -> str:
        return subprocess.run(
            [str(self.bin_dir / tool), "-n", self.node_name(i), *args],
            env=self.env(i),
            check=True,
            capture_output=True,
            text=True,
            timeout=timeout_s,
        ).stdout

    def start_node(self, i: int) -> None:
        base = self.root / f"rg{i}"
        base.mkdir(exist_ok=True)
        (base / "rabbitmq.conf").write_text(
            "\n".join(
                [
                    "loopback_users = none",
                    f"mqtt.listeners.tcp.default = {HOST}:{self.mqtt_ports[i]}",
                    "mqtt.allow_anonymous = false",
                    "mqtt.vhost = /",
                    "mqtt.exchange = amq.topic",
                    f"management.tcp.ip = {HOST}",
                    f"management.tcp.port = {self.management_ports[i]}",
                    "log.file.level = warning",
                ]
            )
            + "\n"
        )
        with open(base / "stdout.log", "ab") as log:
            self.procs[i] = subprocess.Popen(
                [str(self.bin_dir / "rabbitmq-server")],
                env=self.env(i),
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )

    def start(self) -> None:
        self.home.mkdir(exist_ok=True)
        cookie = self.home / ".erlang.cookie"
        cookie.write_text(secrets.token_hex(16))
        cookie.chmod(0o400)
        (self.root / "rabbitmq-env.conf").write_text("")
        for i in range(self.nodes):  # the joining nodes start management after the join (PLUGINS)
            (self.root / f"rg{i}").mkdir(exist_ok=True)
            (self.root / f"rg{i}" / "enabled_plugins").write_text(
                f"[{','.join(PLUGINS if i == 0 else PLUGINS[:-1])}].\n"
            )
        # a session of its own, as the nodes': a terminal's Ctrl-C reaches the process that runs the cluster only
        self.epmd = subprocess.Popen(
            ["epmd", "-port", str(self.epmd_port)],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            start_new_session=True,
        )
        wait_port(self.epmd_port, 10)
        for i in range(self.nodes):
            self.start_node(i)
        for i in range(self.nodes):
            self.ctl(i, "wait", str(self.root / f"rg{i}" / "pid"), "--timeout", "120", timeout_s=150)
        with ThreadPoolExecutor() as pool:  # a node's management starts while the next one joins
            enabled = []
            for i in range(1, self.nodes):
                self.ctl(i, "stop_app")
                self.ctl(i, "join_cluster", self.node_name(0))
                self.ctl(i, "start_app")
                enabled.append(pool.submit(self.ctl, i, "enable", PLUGINS[-1], tool="rabbitmq-plugins"))
            for future in enabled:
                future.result()  # kept in the node's enabled_plugins: a restart starts it again
        for i in range(self.nodes):
            wait_port(self.mqtt_ports[i], 60)
            wait_port(self.management_ports[i], 60)

    def definitions(self) -> dict:
        users = [
            {
                "name": SERVICE_USER,
                "password_hash": rabbit_password_hash(self.secret),
                "hashing_algorithm": "rabbit_password_hashing_sha256",
                "tags": ["administrator"],
            }
        ]
        permissions = [{"user": SERVICE_USER, "vhost": "/", "configure": ".*", "write": ".*", "read": ".*"}]
        topic_permissions = []
        for v in self.vehicles:
            users.append(
                {
                    "name": v,
                    "password_hash": rabbit_password_hash(self.secret),
                    "hashing_algorithm": "rabbit_password_hashing_sha256",
                    "tags": [],
                }
            )
            permissions.append(
                {
                    "user": v,
                    "vhost": "/",
                    "configure": "^mqtt-subscription-.*",
                    "write": "^amq\\.topic$",
                    "read": "^amq\\.topic$",
                }
            )
            topic_permissions.append(
                {
                    "user": v,
                    "vhost": "/",
                    "exchange": "amq.topic",
                    "write": f"^roadgrip\\.v1\\.vehicles\\.{v}\\.(telemetry|observations|heartbeat)$",
                    "read": "^$",
                }
            )
        return {
            "rabbit_version": "3.10.8",
            "users": users,
            "vhosts": [{"name": "/"}],
            "permissions": permissions,
            "topic_permissions": topic_permissions,
            **topology(self.partitions),
        }

    def setup(self) -> None:
        path = self.root / "definitions.json"
        path.write_text(json.dumps(self.definitions()))
        self.ctl(0, "import_definitions", str(path))

    def leader_of_partition(self, partition: int) -> int:
        out = self.ctl(0, "list_queues", "-q", "--formatter", "json", "name", "leader")
        leader = next(q["leader"] for q in json.loads(out) if q["name"] == partition_queue(partition))
        return [self.node_name(i) for i in range(self.nodes)].index(leader)

    def describe(self) -> dict:
        out = self.ctl(0, "list_queues", "-q", "--formatter", "json", "name", "type", "leader", "members")
        running = json.loads(self.ctl(0, "cluster_status", "--formatter", "json"))["running_nodes"]
        return {"running_nodes": running, "queues": json.loads(out)}

    def amqp_url(self, i: int) -> str:
        """The service user's AMQP URL on node i (for workers)."""
        return f"amqp://{SERVICE_USER}:{self.secret}@{HOST}:{self.amqp_ports[i]}/%2F"

    def management_url(self, i: int) -> str:
        """The management HTTP API of node i (log in as the service user)."""
        return f"http://{HOST}:{self.management_ports[i]}"

    def mqtt_url(self, i: int) -> str:
        return f"mqtt://{HOST}:{self.mqtt_ports[i]}"

    def pid(self, i: int) -> int:
        return int((self.root / f"rg{i}" / "pid").read_text().strip())

    def kill(self, i: int) -> None:
        os.kill(self.pid(i), signal.SIGKILL)
        self.procs[i].wait()

    def restart(self, i: int) -> None:
        """Start node i again after `kill`: it rejoins the cluster with its data (its quorum queue members catch
        up from the leaders); returns once its app runs and its MQTT and management listeners answer."""
        pid_file = self.root / f"rg{i}" / "pid"
        pid_file.unlink(missing_ok=True)  # the killed node's: `rabbitmqctl wait` would watch that process
        self.start_node(i)
        self.ctl(i, "wait", str(pid_file), "--timeout", "120", timeout_s=150)
        wait_port(self.mqtt_ports[i], 60)
        wait_port(self.management_ports[i], 60)

    def stop(self) -> None:
        """SIGTERM to every node's process group (the server script, beam.smp and its helpers), SIGKILL to those
        left after NODE_STOP_S; then epmd. Ends within NODE_STOP_S + 2 KILLED_WAIT_S whatever state they are in."""
        running = [p for p in self.procs if p is not None and p.poll() is None]
        for p in running:
            os.killpg(p.pid, signal.SIGTERM)
        deadline = time.monotonic() + NODE_STOP_S
        for p in running:
            try:
                p.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for p in [*self.procs, self.epmd]:
            if p is None:
                continue
            try:
                os.killpg(p.pid, signal.SIGTERM if p is self.epmd else signal.SIGKILL)
            except ProcessLookupError:
                continue  # nothing left of its group
            try:
                p.wait(KILLED_WAIT_S)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
