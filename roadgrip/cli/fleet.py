"""The fleet commands: `roadgrip fleet` (simulated or replayed vehicles against a running cloud), `import-log`
(a recorded log into wire format) and `demo` (the cloud and a small fleet end to end)."""

from __future__ import annotations

import functools
import time
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from roadgrip.cli.common import console, friendly_errors


def _fleet_errors(fn):
    """A fleet that cannot start or reach the cloud ends with its one-line message and exit status 1."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        from roadgrip.fleet.transport import FleetError

        try:
            return fn(*args, **kwargs)
        except (FleetError, OSError) as err:
            console.print(f"[bold red]error:[/] {err}")
            raise typer.Exit(1) from err

    return wrapper


@friendly_errors
@_fleet_errors
def fleet(
    url: str = typer.Option("http://127.0.0.1:8000", help="the running cloud (roadgrip serve)"),
    admin_secret_file: Path = typer.Option(
        Path("roadgrip-data/admin-secret"), help="the cloud's admin secret (or ROADGRIP_ADMIN_SECRET)"
    ),
    vehicles: int = typer.Option(10, min=1, help="simulated vehicles"),
    transport: str = typer.Option("auto", help="auto (MQTT when the cloud has a broker) | mqtt | http"),
    payload: str = typer.Option(
        "json", help="raw vehicles' samples as json | arrow (an Arrow IPC stream, CONTRACTS 3.1)"
    ),
    speed: float = typer.Option(1.0, min=0.01, help="times real time"),
    duration: float = typer.Option(120.0, min=1.0, help="simulated seconds of driving"),
    seed: int = typer.Option(0, help="seed of the plan and the sensors"),
    network_file: Path | None = typer.Option(
        None, "--network", help="roads and patches as GeoJSON (default: the generated network around the Hebei origin)"
    ),
    per_slippery_patch: int = typer.Option(0, min=0, help="vehicles sent to brake on each slippery patch first"),
    prefix: str = typer.Option("fleet", help="vehicle ids are PREFIX-000, PREFIX-001, ..."),
    replay_log: Path | None = typer.Option(None, "--replay", help="replay a recorded log instead of simulating"),
    importer: str | None = typer.Option(None, help="importer of the log (default: detected)"),
    vehicle: str | None = typer.Option(
        None,
        help="profile of the replayed vehicle: a known name or a YAML file "
        "(default: the importer's own, else paper-suv)",
    ),
    mqtt_urls: list[str] | None = typer.Option(
        None,
        "--mqtt",
        help="broker to send to instead of the one the "
        "registration names (repeatable: vehicles are "
        "spread over them, e.g. a cluster's nodes)",
    ),
    mqtt_protocol: str = typer.Option(
        "auto", help="auto (MQTT 5, else 3.1.1 when the broker does not take 5: RabbitMQ 3.10) | 5 | 3.1.1"
    ),
    read_url: str | None = typer.Option(
        None,
        help="after the drive, read each vehicle's estimates and the map back "
        "from this cloud (e.g. another API replica of a cluster)",
    ),
    buffer_messages: int = typer.Option(
        6_000,
        min=1,
        help="MQTT: messages a vehicle keeps until PUBACKed; beyond, new ones are dropped and counted lost",
    ),
    ack_timeout: float = typer.Option(60.0, min=0.0, help="MQTT: seconds to wait for the last PUBACKs after the drive"),
    mode: str = typer.Option(
        "raw",
        help="raw (vehicles send their 10 Hz telemetry) | edge (each runs `roadgrip edge` on its samples and sends "
        "friction observations and heartbeats over MQTT) | mixed (every other vehicle edge)",
    ),
    edge_state_dir: Path | None = typer.Option(
        None, help="edge vehicles' outboxes and estimator states, a folder each (default: a temporary folder)"
    ),
):
    """Drive simulated vehicles (or replay a log) against a running cloud: each vehicle registers, then sends its
    telemetry at 10 Hz with its own credentials, or in edge mode its friction observations (docs/EDGE.md). Over MQTT
    each raw vehicle fails over to the next broker when its connection is lost (docs/FLEET.md, "Failover"). Ends with
    what was sent, acknowledged and lost; exit status 1 when samples or observations were lost (or the fleet could
    not start)."""
    import math
    import os

    from roadgrip.fleet.edge_vehicles import EdgeTerminals, edge_vehicle_ids
    from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, timeline
    from roadgrip.fleet.network import generated_network, network_from_geojson
    from roadgrip.fleet.replay import replay
    from roadgrip.fleet.transport import HttpTerminals, MqttTerminals, read_back, register_fleet

    edge_ids = edge_vehicle_ids([], mode)  # checks the mode before anything starts
    if transport not in ("auto", "mqtt", "http"):
        raise ValueError(f"--transport must be auto, mqtt or http, got {transport!r}")
    if payload not in ("json", "arrow"):
        raise ValueError(f"--payload must be json or arrow, got {payload!r}")
    if mqtt_protocol not in ("auto", "5", "3.1.1"):
        raise ValueError(f"--mqtt-protocol must be auto, 5 or 3.1.1, got {mqtt_protocol!r}")
    secret = os.environ.get("ROADGRIP_ADMIN_SECRET") or (
        admin_secret_file.read_text().strip() if admin_secret_file.is_file() else None
    )
    if not secret:
        raise ValueError(
            f"no admin secret: set ROADGRIP_ADMIN_SECRET or give --admin-secret-file "
            f"({admin_secret_file} does not exist)"
        )
    if replay_log is not None:
        samples, profiles = _replay_samples(replay_log, importer, vehicle, prefix)
    else:
        network = network_from_geojson(network_file) if network_file else generated_network()
        with console.status(f"simulating {vehicles} vehicles..."):
            plans = plan_fleet(
                network, vehicles, duration_s=duration, seed=seed, per_slippery_patch=per_slippery_patch, prefix=prefix
            )
            samples = simulate_fleet(plans, network)
        profiles = {p.vehicle_id: p.vehicle.name for p in plans}
    edge_ids = edge_vehicle_ids(list(profiles), mode)
    secrets, mqtt_url = register_fleet(url, secret, list(profiles.items()))
    brokers = mqtt_urls or ([mqtt_url] if mqtt_url is not None else [])
    use_mqtt = transport == "mqtt" or (transport == "auto" and bool(brokers))
    if (use_mqtt or edge_ids) and not brokers:
        raise ValueError(
            f"{'--transport mqtt' if use_mqtt else f'--mode {mode}'} needs a broker, but the cloud runs without one "
            "(and no --mqtt was given): edge vehicles send over MQTT"
        )
    raw_secrets = {vid: s for vid, s in secrets.items() if vid not in edge_ids}
    terminals = None
    if raw_secrets:
        terminals = (
            MqttTerminals(brokers, raw_secrets, mqtt_protocol, buffer_messages=buffer_messages, payload=payload)
            if use_mqtt
            else HttpTerminals(url, raw_secrets, payload=payload)
        )
    edge = None
    if edge_ids:
        edge = EdgeTerminals(
            brokers,
            {vid: s for vid, s in secrets.items() if vid in edge_ids},
            {vid: profiles[vid] for vid in edge_ids},
            protocol=mqtt_protocol,
            state_dir=edge_state_dir,
        )
    total = sum(len(run) for run in samples.values())
    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console
    ) as bar:
        kinds = f"{len(raw_secrets)} raw over {'MQTT' if use_mqtt else 'HTTP'}, {len(edge_ids)} edge over MQTT"
        task = bar.add_task(f"{len(samples)} vehicles ({kinds}) at {speed:g}x (samples)", total=total)

        def send(batch: list[dict]) -> None:
            vehicle_id = batch[0]["vehicle_id"]
            (edge if vehicle_id in edge_ids else terminals).send(vehicle_id, batch)
            bar.advance(task, len(batch))

        try:
            result = replay(
                timeline(samples, speed, time.time()),
                send,
                speed=speed if speed < 1e6 else math.inf,
                batch=1 if use_mqtt else 10,
            )
        finally:
            bar.update(task, description="waiting for the last acknowledgements")
            if edge is not None:
                edge.close(ack_timeout)
            if terminals is not None and use_mqtt:
                terminals.close(ack_timeout)
            elif terminals is not None:
                terminals.close()
    console.print(
        f"replayed {result.samples:,} samples in {result.batches:,} batches over {result.wall_s:.1f} s "
        f"({result.late_batches} late)"
    )
    lost = 0
    if terminals is not None:
        lost += _report(terminals, len(brokers)) if use_mqtt else _report_http(terminals)
    if edge is not None:
        lost += _report_edge(edge)
    raw_ids = [vid for vid in samples if vid not in edge_ids]
    if read_url is not None and raw_ids:
        with console.status(f"reading the estimates and the map back from {read_url}..."):
            stored = read_back(read_url, secret, raw_ids)
        counts = stored["estimates"]
        console.print(
            f"read back from {read_url}: {sum(counts.values()):,} estimates of "
            f"{sum(1 for n in counts.values() if n)} of {len(counts)} vehicles, {stored['map_cells']} map "
            f"cells ({'settled' if stored['settled'] else 'still growing'} after {stored['wait_s']:.0f} s)"
        )
    if lost:
        raise typer.Exit(1)


PER_VEHICLE_TABLE_MAX = 20  # vehicles: up to this many, a row each


def _report(terminals, brokers: int) -> int:
    """Print what the MQTT fleet sent, had PUBACKed and lost (a row per vehicle when few); return the lost samples."""
    counts = terminals.counts
    total = {f: sum(getattr(c, f) for c in counts.values()) for f in ("sent", "acknowledged", "refused", "dropped")}
    unacked = sum(c.unacknowledged for c in counts.values())
    lost = sum(c.lost for c in counts.values())
    moved = sum(1 for c in counts.values() if c.moves)
    longest = max((c.longest_outage_s for c in counts.values()), default=0.0)
    if len(counts) <= PER_VEHICLE_TABLE_MAX:
        table = Table(title=f"per vehicle, over MQTT {terminals.protocol} to {brokers} broker(s) (samples)")
        for name in ("vehicle", "sent", "PUBACKed", "lost", "moves", "longest outage", "last broker"):
            table.add_column(name, justify="left" if name in ("vehicle", "last broker") else "right")
        for vid, c in counts.items():
            table.add_row(
                vid,
                f"{c.sent:,}",
                f"{c.acknowledged:,}",
                f"{c.lost:,}",
                str(c.moves),
                f"{c.longest_outage_s:.1f} s",
                c.endpoint or "-",
            )
        console.print(table)
    console.print(
        f"fleet over MQTT {terminals.protocol} to {brokers} broker(s): sent {total['sent']:,} samples, "
        f"PUBACKed {total['acknowledged']:,}, lost {lost:,} (buffer full {total['dropped']:,}, refused "
        f"{total['refused']:,}, unacknowledged at the end {unacked:,}); {moved} of {len(counts)} vehicles moved to "
        f"another broker, longest outage {longest:.1f} s"
    )
    return lost


def _report_edge(edge) -> int:
    """Print what the edge vehicles made and sent; return the messages lost."""
    counts = edge.counts.values()
    total = {
        f: sum(getattr(c, f) for c in counts)
        for f in ("samples", "observations", "heartbeats", "sent", "pending", "dropped", "refused")
    }
    console.print(
        f"edge vehicles over MQTT: {len(edge.counts)} estimated {total['samples']:,} samples on board and made "
        f"{total['observations']:,} observations and {total['heartbeats']:,} heartbeats; {total['sent']:,} messages "
        f"sent, lost {edge.lost:,} (still in the outboxes {total['pending']:,}, dropped at the outbox limit "
        f"{total['dropped']:,}, refused {total['refused']:,}); MQTT {edge.protocol}"
    )
    return edge.lost


def _report_http(terminals) -> int:
    console.print(
        f"fleet over HTTP: sent {terminals.sent:,} samples, stored {terminals.stored:,}, rejected "
        f"{terminals.rejected:,}, lost {terminals.lost:,}"
        + (f" (first error: {terminals.error})" if terminals.error else "")
    )
    return terminals.lost


def _replay_samples(
    log: Path, importer: str | None, vehicle: str | None, prefix: str
) -> tuple[dict[str, list[dict]], dict[str, object]]:
    """The log's samples per vehicle (timestamps from 0) and each vehicle's profile (a name or a mapping)."""
    from roadgrip.fleet.importers import resolve_importer
    from roadgrip.fleet.replay import replay_file
    from roadgrip.vehicle.params import VehicleParams

    chosen = resolve_importer(log, importer)
    rows = replay_file(log, chosen, start_ms=0)
    samples: dict[str, list[dict]] = {}
    for row in rows:
        samples.setdefault(f"{prefix}-{row['vehicle_id']}", []).append(
            {**row, "vehicle_id": f"{prefix}-{row['vehicle_id']}"}
        )
    first = min(s["timestamp_ms"] for run in samples.values() for s in run)
    for run in samples.values():
        for s in run:
            s["timestamp_ms"] -= first
    if vehicle is not None:
        profile = VehicleParams.from_yaml(vehicle).to_dict() if vehicle.endswith((".yaml", ".yml")) else vehicle
    elif hasattr(chosen, "profile"):
        profile = chosen.profile().to_dict()
    else:
        profile = "paper-suv"
    return samples, {vid: profile for vid in samples}


@friendly_errors
def import_log(
    input: Path = typer.Argument(..., help="a recorded log: a file or folder that an importer recognises"),
    out: Path = typer.Option(..., help="wire-format telemetry file to write (.csv, .parquet, .ndjson or .jsonl)"),
    importer: str = typer.Option(
        None,
        help="importer name (default: the one that recognises INPUT): "
        "wire | bmw-m8 | can-dbc | any installed through entry points",
    ),
    vehicle_id: str = typer.Option(None, help="vehicle_id of the samples (default: the importer's)"),
    start_ms: int = typer.Option(
        None, help="timestamp of the first sample, ms since the Unix epoch (default: the importer's)"
    ),
):
    """Import a recorded log into wire format v1 (CONTRACTS 3.1), ready for `roadgrip estimate` or a replay."""
    from roadgrip.data.tables import WRITERS, write_table
    from roadgrip.fleet.importers import resolve_importer

    if out.suffix.lower() not in WRITERS:
        raise ValueError(f"--out must end in one of {list(WRITERS)}, got {out.name!r}")
    chosen = resolve_importer(input, importer)
    options = {k: v for k, v in (("vehicle_id", vehicle_id), ("start_ms", start_ms)) if v is not None}
    with console.status(f"importing {input} ({chosen.name})..."):
        table = chosen.load(input, **options)
    write_table(table, out)
    ts = table["timestamp_ms"].to_numpy()
    vehicles = sorted(set(table["vehicle_id"].to_pylist()))
    console.print(
        f"wrote {table.num_rows} samples of {len(vehicles)} vehicle(s) ({', '.join(vehicles[:5])}), "
        f"{(ts.max() - ts.min()) / 1000:.1f} s, to {out} (importer {chosen.name})"
    )
    for key, value in (table.schema.metadata or {}).items():
        if key.startswith(b"roadgrip.") and key != b"roadgrip.importer":
            console.print(f"  {key.decode()[len('roadgrip.') :]}: {value.decode()}")


@friendly_errors
def demo(
    vehicles: int = typer.Option(12, min=1, max=300, help="vehicles in the fleet"),
    speed: float = typer.Option(5.0, min=0.1, help="times real time"),
    duration: float = typer.Option(100.0, min=10.0, help="simulated seconds of driving"),
    seed: int = typer.Option(0, help="seed of the fleet's plan and sensors"),
    mqtt: str = typer.Option("auto", help="auto (Mosquitto when installed, else HTTP) | off | managed"),
    data_dir: Path | None = typer.Option(None, help="keep the cloud's data here (default: a temporary folder)"),
    port: int = typer.Option(0, help="HTTP port (0: a free one)"),
    keep_serving: bool = typer.Option(False, help="leave the cloud running after the summary (Ctrl-C stops it)"),
    mode: str = typer.Option(
        "raw", help="raw (vehicles send telemetry) | edge (vehicles estimate on board and send observations over MQTT)"
    ),
):
    """The main job end to end: start the cloud (and a broker when Mosquitto is installed), drive a small fleet over a
    road network with icy, snowy and wet patches, and summarise the estimates and warnings the cloud produced."""
    from roadgrip.fleet.demo import run_demo

    with Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console
    ) as bar:
        task = bar.add_task("simulating the fleet and starting the cloud", total=None)

        def ready(url: str, dashboard: str) -> None:
            bar.console.print(f"cloud: {url}/docs   dashboard: {dashboard}")
            bar.update(task, description=f"{vehicles} vehicles driving at {speed:g}x real time (samples)")

        report, cloud = run_demo(
            vehicles=vehicles,
            speed=speed,
            duration_s=duration,
            seed=seed,
            data_dir=data_dir,
            port=port,
            mqtt=mqtt,
            mode=mode,
            on_ready=ready,
            progress=lambda done, total: bar.update(task, completed=done, total=total),
        )
    try:
        edge = report.mode == "edge"
        summary = Table(
            title=f"roadgrip demo: {report.vehicles} {'edge ' if edge else ''}vehicles over {report.transport.upper()}"
        )
        summary.add_column("what")
        summary.add_column("value", justify="right")
        rows = (
            (
                ("samples estimated on board", f"{report.samples_sent:,}"),
                ("observations stored", f"{report.observations_stored:,}"),
                ("vehicles with a heartbeat", f"{report.heartbeats_stored:,}"),
            )
            if edge
            else (
                ("samples sent", f"{report.samples_sent:,}"),
                ("telemetry stored", f"{report.telemetry_stored:,}"),
                ("estimates stored", f"{report.estimates_stored:,}"),
                ("share judged excited", f"{report.excited_share:.0%}"),
            )
        )
        for name, value in (*rows, ("streaming wall time", f"{report.stream_wall_s:.1f} s")):
            summary.add_row(name, value)
        console.print(summary)
        warnings = Table(title=f"slippery-road warnings ({len(report.warnings)})")
        for name in (
            "cell",
            "status",
            "reason",
            "latitude",
            "longitude",
            "evidence mu_upper",
            "passes",
            "vehicles",
            "nearest patch",
        ):
            warnings.add_column(
                name, justify="left" if name in ("cell", "status", "reason", "nearest patch") else "right"
            )
        for w in report.warnings:
            warnings.add_row(
                w["cell"],
                w["status"],
                w["reason"],
                f"{w['latitude_deg']:.5f}",
                f"{w['longitude_deg']:.5f}",
                f"{w['mu_upper']:.2f}",
                str(w["n_passes"]),
                str(w["n_vehicles"]),
                f"{w['nearest_patch']} ({w['patch_distance_m']:.0f} m)",
            )
        console.print(warnings)
        console.print(
            "patches: " + ", ".join(f"{p['name']} (mu {p['mu']:.2f}, {p['radius_m']:.0f} m)" for p in report.patches)
        )
        console.print(f"cloud log: {report.log_path}")
        console.print(f"dashboard: {report.dashboard_url}")
        if keep_serving:
            console.print("serving until Ctrl-C")
            while True:
                time.sleep(3600)
    except KeyboardInterrupt:
        pass
    finally:
        cloud.stop()
