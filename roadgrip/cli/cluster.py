"""`roadgrip cluster up`: the cluster mode on one machine (docs/CLUSTER.md), watched until Ctrl-C or SIGTERM."""

from __future__ import annotations

import time
from pathlib import Path

import typer
from rich.table import Table

from roadgrip.cli.common import console, friendly_errors


@friendly_errors
def up(
    data_dir: Path | None = typer.Option(
        None, help="new or empty folder for the cluster's databases, logs and secrets (default: a new temporary folder)"
    ),
    nodes: int = typer.Option(
        3, min=1, help="RabbitMQ nodes joined into one cluster (quorum queues: 3 survive the loss of one)"
    ),
    workers: int = typer.Option(2, min=0, help="`roadgrip worker` processes"),
    apis: int = typer.Option(2, min=0, help="`roadgrip api` replicas"),
    partitions: int = typer.Option(4, min=1, help="partition queues of the vehicles' telemetry"),
    api_port: int = typer.Option(
        0, min=0, max=65535, help="HTTP port of the first API replica, the others on the next ports (0: free ports)"
    ),
    config: Path | None = typer.Option(
        None, help="settings file (YAML) for every worker and API replica; environment variables ROADGRIP_* apply too"
    ),
):
    """A local cluster on 127.0.0.1: RabbitMQ nodes joined into one cluster, PostgreSQL, workers and API replicas,
    each waited for until healthy; restarts a worker, API replica or node that exits (with a backoff and a limit);
    runs until Ctrl-C or SIGTERM, then stops everything it started (docs/CLUSTER.md, "Local cluster")."""
    import logging
    import signal
    import tempfile

    from roadgrip.cloud.cluster.local import ClusterError, LocalCluster

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    data_dir = data_dir or Path(tempfile.mkdtemp(prefix="roadgrip-cluster-"))
    cluster = LocalCluster(
        data_dir, nodes=nodes, workers=workers, apis=apis, partitions=partitions, api_port=api_port, config=config
    )

    stopping = []

    def interrupt(signum, _frame):
        if not stopping:  # the first signal stops the cluster; a second one must not cut that stop short
            stopping.append(signum)
            raise KeyboardInterrupt(signal.Signals(signum).name)

    # Both installed here: a process started in the background of a shell script inherits SIGINT ignored, and Python
    # then installs no KeyboardInterrupt for it (the cause of the Ctrl-C test's flake, issue 25)
    for signum in (signal.SIGINT, signal.SIGTERM):
        signal.signal(signum, interrupt)
    try:
        with console.status("starting the local cluster") as status:
            cluster.start(progress=lambda step: status.update(f"starting the local cluster: {step}..."))
        _print_cluster(cluster)
        while True:
            time.sleep(1.0)
            for line in cluster.supervise(time.monotonic()):
                console.print(f"[bold red]{line}[/]" if "exited" in line else line)
    except KeyboardInterrupt:
        pass
    except ClusterError as err:
        console.print(f"[bold red]error:[/] {err}")
        raise typer.Exit(1) from err
    finally:
        stopping.append("stop")
        console.print("stopping the local cluster (the workers store what they took)...")
        cluster.stop()
        console.print(f"local cluster stopped; its data and logs stay in {cluster.data_dir}")


def _print_cluster(cluster) -> None:
    """What runs where, and the ready line."""
    d = cluster.describe()
    table = Table(title=f"roadgrip local cluster in {d['data_dir']}")
    for name in ("process", "where", "pid", "log"):
        table.add_column(name)
    for node in d["rabbitmq"]:
        table.add_row(
            f"RabbitMQ {node['node']}",
            f"{node['mqtt']}  {node['amqp']}  {node['management']}",
            str(node["pid"]),
            node["log"],
        )
    table.add_row("PostgreSQL", d["postgres"]["url"], str(d["postgres"]["pid"]), d["postgres"]["log"])
    for child in d["workers"]:
        table.add_row(
            child["name"], f"{d['partitions']} partitions, {child['metrics']}", str(child["pid"]), child["log"]
        )
    for child in d["apis"]:
        table.add_row(child["name"], f"{child['url']}/docs", str(child["pid"]), child["log"])
    console.print(table)
    console.print(f"admin secret: {d['admin_secret_file']}   broker user svc's secret: {d['broker_secret_file']}")
    if d["fleet_command"]:
        console.print(f"drive a fleet against it: {d['fleet_command']}")
    console.print(
        f"[bold green]local cluster ready[/] in {cluster.started_s:.0f} s ({d['data_dir']}/cluster.json); "
        "Ctrl-C stops it"
    )
