"""The engine trial of issue 17, item 1: a 3-node NATS 2.9 (JetStream + MQTT listener) or RabbitMQ 3.10 (MQTT plugin,
quorum queues, consistent-hash exchange, single-active-consumer) cluster on 127.0.0.1, simulated vehicles publishing
over MQTT 3.1.1 QoS 1 with a per-vehicle sequence number, one consumer per partition that stores (appends to a file,
fsync) before it acknowledges, and optionally a kill -9 of the node leading partition 0 mid-stream. docs/CLUSTER.md
has the results and the commands.

    python results/trials/cluster/broker_trial.py nats --vehicles 100 --seconds 20 --kill none --out runs/cluster/nats.json
    python results/trials/cluster/broker_trial.py rabbitmq --vehicles 100 --seconds 20 --kill leader --out runs/cluster/rabbit.json

`NatsCluster` and `RabbitCluster` (roadgrip/cloud/transport/amqp.py, also the workers' test fixture) start, kill and stop
the servers (every process they start, by its pid). Needs the Debian packages nats-server and rabbitmq-server
(`apt-get install -y nats-server rabbitmq-server`) and the Python packages nats-py (`pip install -e '.[cluster]'`)
and pika (a dependency of the package: `roadgrip worker` uses it).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing as mp
import os
import secrets
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

from roadgrip.cloud.localhost import free_ports, wait_port
from roadgrip.cloud.transport.amqp import HOST, SERVICE_USER, RabbitCluster, partition_queue

TOPIC = "roadgrip/v1/vehicles/{}/telemetry"
NATS_PARTITION_PREFIX = "rgp"
NATS_MQTT_STREAM = "$MQTT_msgs"
NATS_OWN_STREAM = "RG_TELEMETRY"
MAX_INFLIGHT = 20  # per vehicle, paho's default


def fnv1a_32(text: str) -> int:
    h = 0x811C9DC5
    for b in text.encode():
        h = ((h ^ b) * 0x01000193) & 0xFFFFFFFF
    return h


def vehicle_ids(n: int) -> list[str]:
    return [f"v{i:05d}" for i in range(n)]


class NatsCluster:
    """Three nats-server processes with routes, JetStream and an MQTT listener each. Vehicles' telemetry subjects are
    mapped to `rgp.{{partition(N,1)}}.<subject>`; a vehicle may publish only its own (mapped) telemetry subject.
    Consumers read the server's own `$MQTT_msgs` stream, or with `own_stream` a stream of ours capturing `rgp.>`."""

    name = "nats"

    def __init__(self, root: Path, vehicles: list[str], partitions: int, secret: str, own_stream: bool = False):
        self.root, self.vehicles, self.partitions, self.secret = root, vehicles, partitions, secret
        self.stream = NATS_OWN_STREAM if own_stream else NATS_MQTT_STREAM
        self.filter_prefix = "" if own_stream else "$MQTT.msgs."
        ports = free_ports(12)
        self.client_ports, self.route_ports = ports[0:3], ports[3:6]
        self.mqtt_ports, self.http_ports = ports[6:9], ports[9:12]
        self.procs: list[subprocess.Popen | None] = [None, None, None]

    def node_name(self, i: int) -> str:
        return f"n{i}"

    def config(self, i: int) -> str:
        users = [{"user": SERVICE_USER, "password": self.secret}] + [
            {
                "user": v,
                "password": self.secret,
                "permissions": {
                    "publish": {"allow": [f"{NATS_PARTITION_PREFIX}.*.roadgrip.v1.vehicles.{v}.telemetry"]},
                    "subscribe": {"deny": [">"]},
                },
            }
            for v in self.vehicles
        ]
        mapping = {
            "roadgrip.v1.vehicles.*.telemetry": f"{NATS_PARTITION_PREFIX}.{{{{partition({self.partitions},1)}}}}.roadgrip.v1.vehicles."
            "{{wildcard(1)}}.telemetry"
        }
        routes = ", ".join(f"nats-route://{HOST}:{p}" for p in self.route_ports)
        return "\n".join(
            [
                f"server_name: {self.node_name(i)}",
                f"listen: {HOST}:{self.client_ports[i]}",
                f"http: {HOST}:{self.http_ports[i]}",
                f'jetstream {{ store_dir: "{self.root / f"js{i}"}" }}',
                f"cluster {{ name: rg, listen: {HOST}:{self.route_ports[i]}, routes: [{routes}] }}",
                f"mqtt {{ listen: {HOST}:{self.mqtt_ports[i]} }}",
                "accounts {",
                f"  RG: {{ jetstream: enabled, users: {json.dumps(users)}, mappings: {json.dumps(mapping)} }}",
                f'  SYS: {{ users: [{{user: sys, password: "{self.secret}"}}] }}',
                "}",
                "system_account: SYS",
            ]
        )

    def start_node(self, i: int) -> None:
        conf = self.root / f"n{i}.conf"
        conf.write_text(self.config(i))
        with open(self.root / f"n{i}.log", "ab") as log:  # the server keeps its own copy of the descriptor
            self.procs[i] = subprocess.Popen(["nats-server", "-c", str(conf)], stdout=log, stderr=subprocess.STDOUT)

    def start(self) -> None:
        for i in range(3):
            self.start_node(i)
        for i in range(3):
            wait_port(self.client_ports[i], 20)
            wait_port(self.mqtt_ports[i], 20)

    @property
    def servers(self) -> list[str]:
        return [f"nats://{HOST}:{p}" for p in self.client_ports]

    async def _connect(self):
        import nats

        return await nats.connect(
            servers=self.servers,
            user=SERVICE_USER,
            password=self.secret,
            max_reconnect_attempts=-1,
            reconnect_time_wait=0.2,
            connect_timeout=2,
        )

    def setup(self) -> None:
        """Creates one durable pull consumer per partition on the server's own `$MQTT_msgs` stream (which the first
        MQTT connection creates; its retention is by interest, so the consumers must exist before vehicles publish)."""
        probe = mqtt_client("setup-probe", self.vehicles[0], self.secret)
        probe.connect(HOST, self.mqtt_ports[0])
        probe.loop_start()
        deadline = time.monotonic() + 30
        while not probe.is_connected() and time.monotonic() < deadline:
            time.sleep(0.1)
        probe.disconnect()
        probe.loop_stop()
        asyncio.run(self._setup())

    async def _setup(self) -> None:
        from nats.js.api import AckPolicy, ConsumerConfig, StreamConfig

        nc = await self._connect()
        js = nc.jetstream()
        deadline = time.monotonic() + 30
        while True:
            try:
                await js.stream_info(NATS_MQTT_STREAM)
                break
            except Exception:
                if time.monotonic() > deadline:
                    raise
                await asyncio.sleep(0.2)
        if self.stream == NATS_OWN_STREAM:
            await js.add_stream(
                StreamConfig(name=NATS_OWN_STREAM, subjects=[f"{NATS_PARTITION_PREFIX}.>"], num_replicas=3)
            )
        for p in range(self.partitions):
            await js.add_consumer(
                self.stream,
                ConsumerConfig(
                    durable_name=f"p{p}",
                    filter_subject=f"{self.filter_prefix}{NATS_PARTITION_PREFIX}.{p}.>",
                    ack_policy=AckPolicy.EXPLICIT,
                    ack_wait=5.0,
                    max_ack_pending=10000,
                ),
            )
        await nc.close()

    def leader_of_partition(self, partition: int) -> int:
        """The node leading the stream (every partition lives in that one stream, so one leader for all)."""

        async def leader() -> str:
            nc = await self._connect()
            info = await nc.jetstream().stream_info(self.stream)
            await nc.close()
            return info.cluster.leader

        name = asyncio.run(leader())
        return [self.node_name(i) for i in range(3)].index(name)

    def describe(self) -> dict:
        async def info():
            nc = await self._connect()
            si = await nc.jetstream().stream_info(self.stream)
            await nc.close()
            return {
                "stream": self.stream,
                "replicas": si.config.num_replicas,
                "retention": si.config.retention,
                "leader": si.cluster.leader,
                "followers": [r.name for r in si.cluster.replicas],
            }

        return asyncio.run(info())

    def kill(self, i: int) -> None:
        self.procs[i].send_signal(signal.SIGKILL)
        self.procs[i].wait()

    def stop(self) -> None:
        for p in self.procs:
            if p is not None and p.poll() is None:
                p.terminate()
        for p in self.procs:
            if p is not None:
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
                    p.wait()


def mqtt_client(client_id: str, user: str, secret: str, protocol=paho.MQTTv311) -> paho.Client:
    client = paho.Client(
        CallbackAPIVersion.VERSION2,
        client_id=client_id,
        protocol=protocol,
        **({"clean_session": True} if protocol != paho.MQTTv5 else {}),
    )
    client.username_pw_set(user, secret)
    return client


def probe_mqtt5(port: int, user: str, secret: str) -> str:
    """What an MQTT 5 CONNECT gets from the broker."""
    client = mqtt_client(f"{user}-mqtt5", user, secret, paho.MQTTv5)
    answer = []
    client.on_connect = lambda c, u, flags, rc, props: answer.append(f"CONNACK {rc}")
    client.on_disconnect = lambda c, u, flags, rc, props: answer.append(f"disconnected: {rc}")
    try:
        client.connect(HOST, port, keepalive=5)
        deadline = time.monotonic() + 5
        while not answer and time.monotonic() < deadline:
            client.loop(0.2)
    except OSError as exc:
        answer.append(f"error: {exc!r}")
    client.disconnect()
    return "; ".join(answer) or "no answer within 5 s"


def probe_foreign_publish(port: int, user: str, other: str, secret: str) -> dict:
    """`user` publishes one QoS 1 message to `other`'s telemetry topic: is it PUBACKed, is the connection closed?"""
    client = mqtt_client(f"{user}-probe", user, secret)
    events = {"puback": False, "disconnected": None}
    client.on_publish = lambda c, u, mid, rc, props: events.update(puback=True)
    client.on_disconnect = lambda c, u, flags, rc, props: events.update(disconnected=str(rc))
    client.connect(HOST, port)
    client.loop_start()
    time.sleep(0.5)
    client.publish(TOPIC.format(other), json.dumps({"vehicle_id": "FOREIGN", "seq": 0, "by": user}), qos=1)
    time.sleep(2)
    client.disconnect()
    client.loop_stop()
    return events


def payload(vehicle: str, seq: int) -> str:
    samples = [
        {
            "timestamp": round(seq + k / 10, 1),
            "speed": 22.5,
            "ax": 0.12,
            "ay": -0.03,
            "yaw_rate": 0.01,
            "steering_angle": 0.02,
            "wheel_speed_fl": 22.4,
            "wheel_speed_fr": 22.5,
            "wheel_speed_rl": 22.5,
            "wheel_speed_rr": 22.6,
            "lat": 48.1,
            "lon": 11.5,
        }
        for k in range(10)
    ]
    return json.dumps({"vehicle_id": vehicle, "seq": seq, "samples": samples})


def run_vehicles(
    ports: list[int], vehicles: list[str], secret: str, seconds: float, rate: float, out: str, publishing: mp.Event
) -> None:
    """One paho client per vehicle, spread over the nodes' MQTT ports; on a lost connection a vehicle reconnects
    to the next node. A PUBACK is matched to its message by packet id (fewer than 65,536 messages per vehicle). Publishes for `seconds` (`rate` messages/s in all, 0 = as fast as the PUBACKs come, at most
    MAX_INFLIGHT unacknowledged per vehicle), then waits up to 30 s for the last PUBACKs."""
    clients, sent, acks, infos = {}, {}, {}, {}
    for k, v in enumerate(vehicles):
        client = mqtt_client(v, v, secret)
        client.max_inflight_messages_set(MAX_INFLIGHT)
        client.reconnect_delay_set(0.1, 1.0)
        state = {"node": k % len(ports)}

        def on_disconnect(c, u, flags, rc, props, state=state):
            state["node"] = (state["node"] + 1) % len(ports)
            c.connect_async(HOST, ports[state["node"]])

        def on_publish(c, u, mid, rc, props, v=v):
            acks[v].append((mid, time.monotonic()))

        client.on_disconnect = on_disconnect
        client.on_publish = on_publish
        client.connect(HOST, ports[state["node"]])
        client.loop_start()
        clients[v], sent[v], acks[v], infos[v] = client, 0, [], []
    time.sleep(1)
    publishing.set()
    start = time.monotonic()
    n = 0
    while (now := time.monotonic()) - start < seconds:
        if rate:
            due = int((now - start) * rate)
            while n < due:
                v = vehicles[n % len(vehicles)]
                infos[v].append((sent[v], clients[v].publish(TOPIC.format(v), payload(v, sent[v]), qos=1).mid))
                sent[v] += 1
                n += 1
            time.sleep(0.005)
        else:
            progressed = False
            for v in vehicles:
                if sent[v] - len(acks[v]) < MAX_INFLIGHT:
                    infos[v].append((sent[v], clients[v].publish(TOPIC.format(v), payload(v, sent[v]), qos=1).mid))
                    sent[v] += 1
                    progressed = True
            if not progressed:
                time.sleep(0.001)
    publish_s = time.monotonic() - start
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline and any(sent[v] > len(acks[v]) for v in vehicles):
        time.sleep(0.1)
    result = {"publish_s": publish_s, "start": start, "vehicles": {}}
    for v in vehicles:
        clients[v].disconnect()
        clients[v].loop_stop()
        acked_mids = {mid for mid, _ in acks[v]}
        result["vehicles"][v] = {
            "sent": sent[v],
            "acked": [seq for seq, mid in infos[v] if mid in acked_mids],
            "ack_times": [t for _, t in acks[v]],
        }
    Path(out).write_text(json.dumps(result))


async def nats_consume(cluster: NatsCluster, partition: int, store: Path, stop: threading.Event) -> None:
    import nats.errors

    nc = await cluster._connect()
    js = nc.jetstream()
    sub = None
    with open(store, "a") as f:  # noqa: ASYNC230 - the blocking write and fsync are the durable store measured
        while not stop.is_set():
            try:
                if sub is None:
                    sub = await js.pull_subscribe_bind(f"p{partition}", cluster.stream)
                msgs = await sub.fetch(200, timeout=0.5)
            except nats.errors.TimeoutError:
                continue
            except Exception:  # noqa: BLE001 - a node killed mid-run: whatever the client raises, bind again
                sub = None
                await asyncio.sleep(0.2)
                continue
            now = time.time()
            for m in msgs:
                body = json.loads(m.data)
                f.write(
                    f"{now:.4f} {body['vehicle_id']} {body['seq']} 0 {m.metadata.sequence.stream} "
                    f"{m.metadata.num_delivered}\n"
                )
            f.flush()
            os.fsync(f.fileno())
            for m in msgs:
                try:
                    await m.ack()
                except Exception:  # noqa: BLE001 - unacknowledged messages are redelivered: the trial counts them
                    break
    await nc.close()


def nats_consumers(cluster: NatsCluster, stores: list[Path], stop: threading.Event) -> None:
    async def main():
        await asyncio.gather(*(nats_consume(cluster, p, s, stop) for p, s in enumerate(stores)))

    asyncio.run(main())


def rabbit_consume(cluster: RabbitCluster, partition: int, instance: int, store: Path, stop: threading.Event) -> None:
    """One consumer of partition `partition`'s queue (single-active-consumer: of several, one gets messages)."""
    import pika

    node = instance % 3
    credentials = pika.PlainCredentials(SERVICE_USER, cluster.secret)
    with open(store, "a") as f:
        while not stop.is_set():
            try:
                conn = pika.BlockingConnection(
                    pika.ConnectionParameters(
                        HOST,
                        cluster.amqp_ports[node],
                        credentials=credentials,
                        heartbeat=5,
                        blocked_connection_timeout=5,
                        connection_attempts=1,
                        socket_timeout=2,
                    )
                )
                ch = conn.channel()
                ch.basic_qos(prefetch_count=500)
                batch = []
                for method, _props, body in ch.consume(partition_queue(partition), inactivity_timeout=0.05):
                    if method is not None:
                        batch.append((method.delivery_tag, json.loads(body)))
                    if batch and (method is None or len(batch) >= 200):
                        now = time.time()
                        f.writelines(f"{now:.4f} {b['vehicle_id']} {b['seq']} {instance}\n" for _, b in batch)
                        f.flush()
                        os.fsync(f.fileno())
                        ch.basic_ack(batch[-1][0], multiple=True)
                        batch = []
                    if stop.is_set():
                        break
                conn.close()
            except Exception:  # noqa: BLE001 - a node killed mid-run: whatever pika raises, try the next node
                node = (node + 1) % 3
                time.sleep(0.2)


def rabbit_consumers(cluster: RabbitCluster, stores: list[Path], stop: threading.Event) -> None:
    threads = [
        threading.Thread(target=rabbit_consume, args=(cluster, p, inst, s, stop))
        for p, s in enumerate(stores)
        for inst in (0, 1)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def read_stores(stores: list[Path]) -> list[list[tuple[float, str, int, int]]]:
    out = []
    for s in stores:
        rows = []
        for line in s.read_text().splitlines():
            t, v, seq, inst = line.split()[:4]
            rows.append((float(t), v, int(seq), int(inst)))
        out.append(rows)
    return out


def analyse(vehicles_result: dict, stored: list[list[tuple]], kill_time: float | None, partitions_of: dict) -> dict:
    acked = {(v, s) for v, r in vehicles_result["vehicles"].items() for s in r["acked"]}
    sent = sum(r["sent"] for r in vehicles_result["vehicles"].values())
    seen, dups, disorder, foreign, max_seq, instances = set(), 0, 0, 0, {}, {}
    partition_mismatch = 0
    for p, rows in enumerate(stored):
        for _, v, seq, inst in rows:
            if v == "FOREIGN":
                foreign += 1
                continue
            if partitions_of and partitions_of[v] != p:
                partition_mismatch += 1
            instances.setdefault(v, set()).add(inst)
            if (v, seq) in seen:
                dups += 1
                continue
            seen.add((v, seq))
            if seq < max_seq.get(v, -1):
                disorder += 1
            max_seq[v] = max(seq, max_seq.get(v, -1))
    lost = acked - seen
    all_times = sorted(t for rows in stored for t, *_ in rows)
    result = {
        "sent": sent,
        "acked": len(acked),
        "stored_unique": len(seen),
        "duplicates": dups,
        "lost_acked": len(lost),
        "lost_examples": sorted(lost)[:10],
        "out_of_order": disorder,
        "foreign_stored": foreign,
        "partition_mismatch": partition_mismatch,
        "vehicles_served_by_two_consumers": sum(len(i) > 1 for i in instances.values()),
        "ack_rate_per_s": len(acked) / vehicles_result["publish_s"],
    }
    if all_times:
        result["store_span_s"] = all_times[-1] - all_times[0]
    if kill_time is not None:
        gaps = []
        for rows in stored:
            times = [t for t, *_ in rows]
            before = [t for t in times if t <= kill_time]
            after = [t for t in times if t > kill_time]
            if after:
                gaps.append(after[0] - (before[-1] if before else kill_time))
        result["consumer_gap_across_kill_s"] = max(gaps) if gaps else None
        offset = time.time() - time.monotonic()
        pub_gaps = []
        for r in vehicles_result["vehicles"].values():
            times = [t + offset for t in r["ack_times"]]
            before = [t for t in times if t <= kill_time]
            after = [t for t in times if t > kill_time]
            if after:
                pub_gaps.append(after[0] - (before[-1] if before else kill_time))
        result["vehicle_puback_gap_across_kill_s_max"] = max(pub_gaps) if pub_gaps else None
    return result


def trial(args) -> dict:
    root = Path(tempfile.mkdtemp(prefix=f"broker-trial-{args.broker}-"))
    vehicles = vehicle_ids(args.vehicles)
    secret = secrets.token_hex(8)
    if args.broker == "nats":
        cluster = NatsCluster(root, vehicles, args.partitions, secret, own_stream=args.nats_stream == "own")
    else:
        cluster = RabbitCluster(root, vehicles, args.partitions, secret)
    report = {
        "broker": args.broker,
        "nats_stream": args.nats_stream,
        "vehicles": args.vehicles,
        "partitions": args.partitions,
        "seconds": args.seconds,
        "rate": args.rate,
        "kill": args.kill,
        "cpus": os.cpu_count(),
    }
    stop = threading.Event()
    consumer = None
    try:
        t0 = time.monotonic()
        cluster.start()
        cluster.setup()
        report["cluster_start_s"] = round(time.monotonic() - t0, 1)
        report["version"] = subprocess.run(
            ["nats-server", "--version"]
            if args.broker == "nats"
            else ["dpkg-query", "-W", "-f=${Version}", "rabbitmq-server"],
            capture_output=True,
            text=True,
            check=False,
        ).stdout.strip()
        report["cluster"] = cluster.describe()
        report["mqtt5_connect"] = probe_mqtt5(cluster.mqtt_ports[0], vehicles[0], secret)
        stores = [root / f"store-p{p}.log" for p in range(args.partitions)]
        for s in stores:
            s.touch()
        target = nats_consumers if args.broker == "nats" else rabbit_consumers
        consumer = threading.Thread(target=target, args=(cluster, stores, stop))
        consumer.start()
        time.sleep(1)
        report["foreign_publish"] = probe_foreign_publish(cluster.mqtt_ports[1], vehicles[0], vehicles[1], secret)
        ctx = mp.get_context("spawn")
        publishing = ctx.Event()
        out = root / "vehicles.json"
        pub = ctx.Process(
            target=run_vehicles,
            args=(cluster.mqtt_ports, vehicles, secret, args.seconds, args.rate, str(out), publishing),
        )
        pub.start()
        publishing.wait(60)
        kill_time = None
        if args.kill != "none":
            time.sleep(args.seconds / 2)
            node = cluster.leader_of_partition(0)
            kill_time = time.time()
            cluster.kill(node)
            report["killed"] = cluster.node_name(node)
        pub.join()
        result = json.loads(out.read_text())
        acked_total = sum(len(r["acked"]) for r in result["vehicles"].values())
        deadline = time.monotonic() + args.drain_s
        while time.monotonic() < deadline:
            if sum(len(s.read_text().splitlines()) for s in stores) >= acked_total:
                break
            time.sleep(0.5)
        time.sleep(1)
        stop.set()
        consumer.join(30)
        partitions_of = {v: fnv1a_32(v) % args.partitions for v in vehicles} if args.broker == "nats" else {}
        report.update(analyse(result, read_stores(stores), kill_time, partitions_of))
        if args.broker == "rabbitmq":
            counts = {}
            for p, rows in enumerate(read_stores(stores)):
                counts[p] = len({v for _, v, *_ in rows})
            report["vehicles_per_partition"] = counts
    finally:
        stop.set()
        if consumer is not None:
            consumer.join(30)
        cluster.stop()
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
        else:
            report["root"] = str(root)
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("broker", choices=["nats", "rabbitmq"])
    parser.add_argument("--vehicles", type=int, default=100)
    parser.add_argument("--partitions", type=int, default=4)
    parser.add_argument("--seconds", type=float, default=20)
    parser.add_argument("--rate", type=float, default=0, help="messages/s in all; 0: as fast as PUBACKs come")
    parser.add_argument(
        "--kill",
        choices=["none", "leader"],
        default="none",
        help="leader: kill -9 the node leading partition 0 halfway through",
    )
    parser.add_argument(
        "--nats-stream",
        choices=["mqtt", "own"],
        default="mqtt",
        help="nats: consume the server's $MQTT_msgs stream, or a stream of ours capturing rgp.>",
    )
    parser.add_argument("--drain-s", type=float, default=60)
    parser.add_argument("--keep", action="store_true", help="keep the servers' directory and logs")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    report = trial(args)
    text = json.dumps(report, indent=1)
    print(text)
    if args.out:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(text + "\n")


if __name__ == "__main__":
    main()
