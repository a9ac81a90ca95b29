"""How long a 3-node RabbitCluster (roadgrip/cloud/transport/amqp.py) takes to start and load its definitions, as
every cluster test module, `roadgrip cluster up` and `roadgrip bench cluster` start one; then one MQTT CONNECT per
node (each must answer Success) and the cluster's state (3 running nodes, 3 members per queue), so that a faster
start is also a working one.

    python results/trials/suite/rabbit_start.py            # the working tree's RabbitCluster
    python results/trials/suite/rabbit_start.py --rev REV  # RabbitCluster as of git revision REV (its amqp.py only)

Prints one JSON line. A run record of the suite's work, not a benchmark of the product (those are `roadgrip bench`).
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import paho.mqtt.client as paho
from paho.mqtt.enums import CallbackAPIVersion

VEHICLES = ["v1", "v2", "v3"]
SECRET = "rabbit-start-secret"


def rabbit_cluster_class(rev: str | None):
    if rev is None:
        from roadgrip.cloud.transport.amqp import RabbitCluster

        return RabbitCluster
    source = subprocess.run(
        ["git", "show", f"{rev}:roadgrip/cloud/transport/amqp.py"], check=True, capture_output=True, text=True
    ).stdout
    path = Path(tempfile.mkdtemp(prefix="rabbit-start-")) / "amqp_at_rev.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location("amqp_at_rev", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.RabbitCluster


def connack(port: int, vehicle: str) -> str:
    answered, codes = threading.Event(), []
    client = paho.Client(CallbackAPIVersion.VERSION2, client_id=vehicle, protocol=paho.MQTTv311)
    client.username_pw_set(vehicle, SECRET)
    client.on_connect = lambda c, userdata, flags, code, properties=None: (codes.append(str(code)), answered.set())
    client.connect("127.0.0.1", port)
    client.loop_start()
    answered.wait(30)
    client.loop_stop()
    client.disconnect()
    return codes[0] if codes else "no answer"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rev", help="git revision whose RabbitCluster to start (default: the working tree's)")
    args = parser.parse_args()
    cluster = rabbit_cluster_class(args.rev)(Path(tempfile.mkdtemp(prefix="rabbit-start-")), VEHICLES, 4, SECRET, 3)
    try:
        started = time.monotonic()
        cluster.start()
        cluster.setup()
        start_s = time.monotonic() - started
        connacks = [connack(cluster.mqtt_ports[i], v) for i, v in enumerate(VEHICLES)]
        described = cluster.describe()
    finally:
        stopping = time.monotonic()
        cluster.stop()
        stop_s = time.monotonic() - stopping
    print(
        json.dumps(
            {
                "rev": args.rev or "working tree",
                "start_and_definitions_s": round(start_s, 1),
                "stop_s": round(stop_s, 1),
                "connacks": connacks,
                "running_nodes": len(described["running_nodes"]),
                "queue_members": sorted({len(q["members"]) for q in described["queues"]}),
                "loadavg_1min": float(Path("/proc/loadavg").read_text().split()[0]),
            }
        )
    )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
