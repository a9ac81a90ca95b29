"""`roadgrip bench sim|estimate|ingest|cluster|failover|uplink`: run the benchmarks of roadgrip/bench and print their tables."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.table import Table

from roadgrip.cli.common import console, friendly_errors


@friendly_errors
def estimate(
    estimators: list[str] = typer.Option(
        ["pmf", "ekf", "ukf", "default"], "--estimator", help="estimators (repeatable)"
    ),
    updates: int = typer.Option(20000, help="streamed updates per estimator"),
    channel_set: list[str] = typer.Option(
        [],
        "--channel-set",
        help="stream only these optional channels: base, gnss, forces, steering or all (repeatable: a row each)",
    ),
    channels: bool = typer.Option(False, help="the stream carries every optional channel: --channel-set all"),
):
    """Vehicle updates per second per core and per-update latency of each estimator, streaming one sample at a time."""
    from roadgrip.bench.estimate import bench_estimators, format_bench
    from roadgrip.bench.sim import machine_description

    sets = tuple(dict.fromkeys([*channel_set, *(["all"] if channels else [])]))
    with console.status("benchmarking the estimators..."):
        rows = bench_estimators(tuple(estimators), updates, sets)
    console.print(format_bench(rows), markup=False)
    console.print(f"machine: {machine_description()}")


@friendly_errors
def ingest(
    vehicles: int = typer.Option(1000, min=1, help="simulated vehicles, each sending at 10 Hz"),
    seconds: float = typer.Option(30.0, min=1.0, help="duration of each case"),
    transport: list[str] = typer.Option(["mqtt", "http"], help="mqtt and/or http (repeatable)"),
    http_batch: int = typer.Option(10, min=1, help="samples per HTTP request (10: a terminal posting once a second)"),
    mqtt_batch: int = typer.Option(1, min=1, help="samples per MQTT message (1: every 100 ms)"),
    database_url: str | None = typer.Option(None, help="PostgreSQL URL (default: SQLite in a scratch folder)"),
    ingest_processes: int = typer.Option(
        0, min=0, help="the service's ingest processes (0: ingest in the service's own process; docs/CLOUD.md)"
    ),
    out: Path | None = typer.Option(None, help="write the results as JSON here"),
    mode: str = typer.Option(
        "raw",
        help="raw (vehicles send telemetry) | edge (vehicles send friction observations over MQTT, each its own "
        "login, roadgrip/bench/ingest_edge.py: exactly once, map latency, memory, CPU per stored observation)",
    ),
    edge_rate: float = typer.Option(
        1.0, min=0.001, help="edge mode: observations per vehicle per second (the agent's: 0.035, docs/EDGE.md)"
    ),
):
    """Vehicles at 10 Hz end to end (ingest, estimate, stored) over MQTT and HTTP, counting what was sent,
    acknowledged and stored; beside it the broker and the database alone, measured in the same run. Mode edge:
    observations instead, a soak: stored exactly once, the map's latency, the service's memory over time and its CPU
    per stored observation (docs/EDGE.md)."""
    import json

    if mode not in ("raw", "edge"):
        raise ValueError(f"--mode must be raw or edge, got {mode!r}")
    if mode == "edge":
        from roadgrip.bench.ingest_edge import format_edge_case, observation_templates, run_edge_case

        with console.status("the vehicle end on the fleet benchmark's drives..."):
            templates = observation_templates()
        with console.status(f"edge: {vehicles} vehicles x {edge_rate:g} observations/s for {seconds:.0f} s..."):
            row = run_edge_case(vehicles, seconds, edge_rate, templates, progress=lambda m: None)
        console.print(format_edge_case(row))
        if out is not None:
            out.write_text(json.dumps(row, indent=1))
        return

    from roadgrip.bench.ingest import (
        IngestCase,
        broker_ceiling,
        database_ceiling,
        format_ingest,
        plot_timelines,
        run_case,
        sample_bodies,
    )
    from roadgrip.bench.sim import machine_description

    for t in transport:
        if t not in ("mqtt", "http"):
            raise ValueError(f"--transport must be mqtt or http, got {t!r}")
    with console.status("simulating the telemetry..."):
        bodies = sample_bodies()
    rows = []
    for t in transport:
        case = IngestCase(
            t, vehicles, seconds, mqtt_batch if t == "mqtt" else http_batch, ingest_processes=ingest_processes
        )
        with console.status(f"{t}: {vehicles} vehicles for {seconds:.0f} s..."):
            rows.append(run_case(case, bodies, database_url, progress=lambda m: None))
    ceilings = []
    with console.status("the database alone..."):
        ceilings.append(database_ceiling(bodies, database_url))
    if "mqtt" in transport:
        with console.status("the broker alone..."):
            ceilings.append(broker_ceiling(bodies, vehicles, min(seconds, 20.0), mqtt_batch))
    console.print(format_ingest(rows))
    for c in ceilings:
        rate = c.get("rows_per_s", c.get("samples_per_s"))
        console.print(f"ceiling, {c['case']}: {rate:,.0f} samples per s")
    console.print(f"machine: {machine_description()}")
    if out is not None:
        out.write_text(json.dumps({"cases": rows, "ceilings": ceilings, "machine": machine_description()}, indent=1))
        console.print(
            f"results: {out}; memory, backlog and latency over time: {plot_timelines(rows, out.with_suffix('.png'))}"
        )


@friendly_errors
def cluster(
    vehicles: int = typer.Option(500, min=1, help="simulated vehicles, each its own MQTT 3.1.1 connection"),
    seconds: float = typer.Option(20.0, min=1.0, help="measuring window of each case"),
    workers: str = typer.Option("1,2,4", help="worker counts to measure, comma-separated"),
    partitions: int = typer.Option(8, min=1, help="partition queues"),
    rate: float = typer.Option(
        1.0,
        min=0.0,
        help="messages of 10 samples a second per vehicle in the worker cases "
        "(1: a terminal; 0: as fast as PUBACKs allow)",
    ),
    payload: str = typer.Option("json", help="the vehicles' messages: json | arrow (an Arrow IPC stream)"),
    out: Path | None = typer.Option(None, help="write the results as JSON here"),
):
    """Cluster mode's capacity on this machine (docs/CLUSTER.md, "Capacity"): 3 RabbitMQ nodes and PostgreSQL on
    127.0.0.1, vehicles publishing MQTT 3.1.1 QoS 1: the broker's own ceiling (as fast as PUBACKs allow, ack-only
    consumers), then stored samples per second with each count of `roadgrip worker` processes (vehicles at --rate),
    each for a fixed window."""
    from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

    from roadgrip.bench.cluster import ClusterBench, format_cluster_bench, run_cluster_bench, write_json

    try:
        counts = tuple(int(w) for w in workers.split(","))
    except ValueError:
        raise ValueError(f"--workers must be comma-separated counts like 1,2,4, got {workers!r}") from None
    bench = ClusterBench(vehicles, seconds, counts, partitions, rate, payload)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("starting", total=1.0)
        result = run_cluster_bench(
            bench,
            lambda message, fraction: bar.update(
                task, description=message, **({} if fraction is None else {"completed": fraction})
            ),
        )
    console.print(format_cluster_bench(result))
    console.print(f"machine: {result['machine']}; {result['elapsed_s']:.0f} s in all")
    if out is not None:
        write_json(result, out)
        console.print(f"results: {out}")


@friendly_errors
def sim(
    runs: int = typer.Option(256, help="runs in the batch case"),
    seed: int = typer.Option(0, help="seed of the scenarios"),
):
    """Simulated seconds per wall-clock second: one run, the paper preset, a batch."""
    from roadgrip.bench.sim import bench_sim, machine_description

    with console.status("benchmarking the simulator..."):
        rows = bench_sim(runs, seed)
    table = Table(title="roadgrip bench sim")
    for name in ("case", "runs", "simulated s", "wall s", "x real time"):
        table.add_column(name, justify="left" if name == "case" else "right")
    for row in rows:
        table.add_row(
            row["case"],
            str(row["runs"]),
            f"{row['simulated_s']:.0f}",
            f"{row['wall_s']:.3f}",
            f"{row['realtime_factor']:,.0f}",
        )
    console.print(table)
    console.print(f"machine: {machine_description()}")


@friendly_errors
def failover(
    data_dir: Path = typer.Option(..., help="a new or empty folder for the local cluster (kept, with its logs)"),
    vehicles: int = typer.Option(20, min=1, max=300, help="simulated vehicles at real time over MQTT 3.1.1"),
    duration: float = typer.Option(100.0, min=10.0, help="seconds of driving"),
    worker_kill: float = typer.Option(30.0, help="seconds into the drive: worker 0 killed (SIGKILL)"),
    node_kill: float = typer.Option(50.0, help="seconds into the drive: RabbitMQ node --node killed (SIGKILL)"),
    node_restart: float = typer.Option(70.0, help="seconds into the drive: that node started again"),
    node: int = typer.Option(1, min=0, max=2, help="the RabbitMQ node killed"),
    out: Path | None = typer.Option(None, help="write the results as JSON here"),
):
    """A Jepsen-style count (docs/RELIABILITY.md): the local cluster of `roadgrip cluster up`, a fleet driving at real
    time; a worker killed, then a RabbitMQ node, then the node restarted. Per vehicle: sent, PUBACKed, stored in
    PostgreSQL, lost, the longest stall, and the partition moves. Exit status 1 when a target of issue 25 is missed."""
    import json

    from roadgrip.bench.failover import FailoverBench, format_failover_bench, run_failover_bench

    bench = FailoverBench(vehicles, duration, worker_kill, node_kill, node_restart, node)
    with console.status("starting the local cluster...") as status:
        result = run_failover_bench(bench, data_dir, lambda message: status.update(message))
    console.print(format_failover_bench(result))
    s = result["summary"]
    console.print(
        f"sent {s['sent']:,}, PUBACKed {s['pubacked']:,}, stored {s['stored']:,}, lost by the client "
        f"{s['lost_by_client']:,}, PUBACKed not stored {s['pubacked_not_stored']:,}; {s['vehicles_on_killed_node']} "
        f"vehicles on the killed node, slowest to resume {s['slowest_resume_s']} s; longest stall "
        f"{s['longest_stall_s']:.1f} s"
    )
    m = result["partition_moves"]
    console.print(
        f"partition moves (spread releases) {m['released_before_worker_kill']} before the worker kill, "
        f"{m['released_from_worker_kill']} from it on; owner changes {m['owner_changes']} "
        f"({m['owner_changes_from_worker_kill']} from the kill on), retakes by the same worker "
        f"{m['retakes_by_the_same_worker']}, partition connections lost {m['lost_connections']}; live workers as "
        f"each worker saw them change: {m['live_workers_seen']}"
    )
    console.print("targets: " + ", ".join(f"{k} {'met' if v else 'MISSED'}" for k, v in s["targets"].items()))
    console.print(f"cluster started in {result['cluster_start_s']:.0f} s; {result['elapsed_s']:.0f} s in all")
    if out is not None:
        out.write_text(json.dumps(result, indent=1))
        console.print(f"results: {out}")
    if not all(s["targets"].values()):
        raise typer.Exit(1)


@friendly_errors
def uplink(
    seed: int = typer.Option(0, help="the fleet benchmark's scenario seed"),
    vehicles: int = typer.Option(8, min=1, help="vehicles of the fleet benchmark's scenario"),
    duration_s: float = typer.Option(3600.0, help="the scenario's length, s"),
):
    """Uplink bytes per vehicle-hour and messages/s per vehicle, raw against edge mode, on the fleet benchmark's
    drives; CPU and peak RSS of one `roadgrip edge` process (docs/EDGE.md)."""
    from roadgrip.bench.uplink import format_uplink, run_uplink_bench

    with console.status("simulating the drives and running the agents..."):
        result = run_uplink_bench(seed, vehicles, duration_s)
    console.print(format_uplink(result))
