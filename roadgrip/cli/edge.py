"""`roadgrip edge`: the vehicle end (roadgrip/edge/, docs/EDGE.md)."""

from __future__ import annotations

import logging
from pathlib import Path

import typer

from roadgrip.cli.common import console, friendly_errors


@friendly_errors
def edge(
    vehicle_id: str = typer.Option(..., help="this vehicle's id (CONTRACTS 3.1), also its MQTT login name"),
    input: str = typer.Option(None, help="wire-format lines (NDJSON) from this file, '-' for stdin"),
    log: Path = typer.Option(None, help="a recorded log, read by the importers of `roadgrip import-log`"),
    importer: str = typer.Option(None, help="the log's importer (default: detected)"),
    can_interface: str = typer.Option(None, help="a python-can interface (socketcan, virtual, ...): read live CAN"),
    can_channel: str = typer.Option(None, help="the CAN interface's channel (can0, ...)"),
    dbc: Path = typer.Option(None, help="the car's DBC (with --can-interface)"),
    mapping: Path = typer.Option(None, help="the CAN mapping file, as import-log's can-dbc importer takes it"),
    vehicle: str = typer.Option(
        None, help="vehicle profile: a YAML file (CONTRACTS 3.2) or a shipped name; default the mapping's or paper-suv"
    ),
    estimator: str = typer.Option("pmf", help="the estimator on board (a name or model file, as `serve` takes it)"),
    mqtt: str = typer.Option(None, help="the cloud's broker, mqtt://host:port; none: observations stay in the outbox"),
    mqtt_protocol: str = typer.Option(
        "5", help="MQTT version: 5 (Mosquitto, `roadgrip serve`) or 3.1.1 (RabbitMQ, `roadgrip cluster up`)"
    ),
    password: str = typer.Option(None, envvar="ROADGRIP_EDGE_PASSWORD", help="this vehicle's secret"),
    state_dir: Path = typer.Option(Path("edge-state"), help="estimator state and outbox (kept across runs)"),
    h3_resolution: int = typer.Option(10, help="the map's H3 resolution (the cloud's h3_resolution)"),
    heartbeat_interval_s: float = typer.Option(300.0, help="seconds of driving between heartbeats"),
    outbox_limit: int = typer.Option(100_000, help="messages the outbox holds; at the limit the oldest is dropped"),
    drain_s: float = typer.Option(10.0, help="at the end, seconds to wait for the outbox to empty"),
) -> None:
    """Estimate friction on board and send friction observations instead of samples (docs/EDGE.md)."""
    from roadgrip.edge.agent import EdgeAgent
    from roadgrip.edge.outbox import Outbox
    from roadgrip.edge.run import run_agent
    from roadgrip.edge.sources import CanSampler, WireLines, log_samples, read_lines
    from roadgrip.edge.uplink import Uplink
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.vehicle.params import PAPER_SUV, VEHICLES, VehicleParams

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    chosen = [name for name, v in (("input", input), ("log", log), ("can-interface", can_interface)) if v is not None]
    if len(chosen) != 1:
        raise ValueError(f"give exactly one of --input, --log, --can-interface, got {chosen or 'none'}")
    if vehicle is None:
        profile = PAPER_SUV
    elif vehicle in VEHICLES:
        profile = VEHICLES[vehicle]
    else:
        profile = VehicleParams.from_yaml(vehicle)
    if can_interface is not None:
        if dbc is None or mapping is None:
            raise ValueError("--can-interface needs --dbc and --mapping")
        import can

        sampler = CanSampler(can.Bus(interface=can_interface, channel=can_channel), dbc, mapping, vehicle_id)
        profile = sampler.mapping.profile if vehicle is None else profile
        samples = sampler
    elif log is not None:
        samples = log_samples(log, importer, vehicle_id=vehicle_id)
    else:
        samples = WireLines(read_lines(input), vehicle_id)
    state_dir.mkdir(parents=True, exist_ok=True)
    outbox = Outbox(state_dir / "outbox.sqlite", outbox_limit)
    agent = EdgeAgent(
        vehicle_id,
        profile,
        load_estimator(estimator),
        outbox,
        state_path=state_dir / "estimator-state.json",
        resolution=h3_resolution,
        heartbeat_interval_s=heartbeat_interval_s,
    )
    uplink = None
    if mqtt is not None:
        if not password:
            raise ValueError("--mqtt needs this vehicle's secret: --password or ROADGRIP_EDGE_PASSWORD")
        uplink = Uplink(mqtt, vehicle_id, password, outbox, protocol=mqtt_protocol)
        uplink.start()
    try:
        summary = run_agent(agent, samples, uplink, drain_s)
    finally:
        if uplink is not None:
            uplink.close()
        outbox.close()
    console.print(
        f"{summary.samples} samples, {summary.observations} observations; {summary.sent_messages} messages sent "
        f"({summary.sent_payload_bytes} payload bytes), {summary.pending} waiting in the outbox, {summary.dropped} "
        f"dropped; estimator state {'restored' if agent.restored else 'new'}; CPU {summary.cpu_s:.2f} s"
    )
