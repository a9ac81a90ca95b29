"""`roadgrip demo`, the main job end to end on one machine: the cloud (with its own Mosquitto when installed, else HTTP
only), a small fleet that drives the generated network through its icy and snowy patches, and a summary of what the
cloud made of it: samples, estimates, warnings and where, and the dashboard's URL.

Mode raw (the default): the vehicles stream their telemetry and the cloud estimates. Mode edge: each vehicle runs the
vehicle end on its samples (roadgrip/fleet/edge_vehicles.py, roadgrip/edge/) and sends friction observations over
MQTT: it needs the broker (Mosquitto installed)."""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import uvicorn

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.localhost import free_port
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.fleet.edge_vehicles import EdgeTerminals
from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, timeline
from roadgrip.fleet.network import Network, generated_network
from roadgrip.fleet.replay import replay
from roadgrip.fleet.transport import HttpTerminals, MqttTerminals, register_fleet


@dataclass
class DemoReport:
    url: str
    dashboard_url: str
    log_path: str
    transport: str
    vehicles: int
    samples_sent: int
    telemetry_stored: int
    estimates_stored: int
    excited_share: float
    stream_wall_s: float
    mode: str = "raw"
    observations_stored: int = 0
    heartbeats_stored: int = 0
    warnings: list[dict] = field(default_factory=list)
    patches: list[dict] = field(default_factory=list)


class LocalCloud:
    """A CloudService and its HTTP server (uvicorn in a thread) on 127.0.0.1."""

    def __init__(self, settings: Settings):
        self.service = CloudService(settings)
        self.service.start()
        config = uvicorn.Config(create_app(self.service), host=settings.host, port=settings.port, log_level="warning")
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, name="roadgrip-http", daemon=True)
        self.thread.start()
        deadline = time.time() + 30
        while not self.server.started:
            if time.time() > deadline or not self.thread.is_alive():
                self.stop()
                raise RuntimeError("the cloud's HTTP server did not start")
            time.sleep(0.05)
        self.url = f"http://{settings.host}:{settings.port}"

    def stop(self) -> None:
        self.server.should_exit = True
        self.thread.join(10)
        self.service.stop()


def settle(service: CloudService, timeout_s: float = 30.0) -> None:
    """Wait until the pipeline has stored everything and released its reorder windows."""
    deadline = time.time() + timeout_s
    time.sleep(service.settings.reorder_window_s + 2 * service.settings.flush_interval_s)
    while service.ingest.backlog and time.time() < deadline:
        time.sleep(0.05)
    time.sleep(service.settings.reorder_window_s + 2 * service.settings.flush_interval_s)


def wait_observations(service: CloudService, made: int, timeout_s: float = 30.0) -> int:
    """Wait until the service has stored `made` observations (the broker PUBACKs an edge vehicle before the service
    has taken the message), or `timeout_s`; how many it holds."""
    deadline = time.time() + timeout_s
    while (stored := len(service.storage.observations_since(0))) < made and time.time() < deadline:
        time.sleep(0.05)
    return stored


def run_demo(
    *,
    vehicles: int = 12,
    speed: float = 5.0,
    duration_s: float = 100.0,
    seed: int = 0,
    data_dir: Path | None = None,
    port: int = 0,
    mqtt: str = "auto",
    mode: str = "raw",
    network: Network | None = None,
    progress=None,
    on_ready=None,
) -> tuple[DemoReport, LocalCloud]:
    """Start the cloud, drive the fleet (`mode` raw or edge), return the report and the still running cloud (the
    caller stops it)."""
    if mode not in ("raw", "edge"):
        raise ValueError(f"demo mode must be raw or edge, got {mode!r}")
    network = network or generated_network()
    data_dir = Path(tempfile.mkdtemp(prefix="roadgrip-demo-")) if data_dir is None else data_dir
    data_dir.mkdir(parents=True, exist_ok=True)
    _log_to(data_dir / "cloud.log")
    # the fleet runs at `speed` times real time, so each vehicle sends `speed` times its 10 Hz: no per-vehicle limit
    settings = Settings(
        data_dir=data_dir, port=port or free_port(), mqtt=mqtt, map_clock="wall", rate_limit_samples_per_s=0
    )
    plans = plan_fleet(
        network,
        vehicles,
        duration_s=duration_s,
        seed=seed,
        patch_braking_share=0.5,
        per_slippery_patch=2,
        prefix="demo",
    )
    samples = simulate_fleet(plans, network)
    cloud = LocalCloud(settings)
    try:
        secrets, mqtt_url = register_fleet(
            cloud.url, cloud.service.admin_secret, [(p.vehicle_id, p.vehicle.name) for p in plans]
        )
        reader = f"dashboard-{int(time.time())}"
        reader_secret = cloud.service.register_reader(reader)
        dashboard = f"{cloud.url}/dashboard#{reader}:{reader_secret}"
        if on_ready is not None:
            on_ready(cloud.url, dashboard)
        if mode == "edge" and not mqtt_url:
            raise RuntimeError("demo --mode edge needs the broker: install Mosquitto (scripts/install_system_deps.sh)")
        if mode == "edge":
            terminals = EdgeTerminals(mqtt_url, secrets, {p.vehicle_id: p.vehicle for p in plans})
        else:
            terminals = MqttTerminals(mqtt_url, secrets) if mqtt_url else HttpTerminals(cloud.url, secrets)
        total, sent = sum(len(run) for run in samples.values()), [0]

        def send(batch: list[dict]) -> None:
            terminals.send(batch[0]["vehicle_id"], batch)
            sent[0] += len(batch)
            if progress is not None:
                progress(sent[0], total)

        result = replay(timeline(samples, speed, time.time()), send, speed=speed, batch=1 if mqtt_url else 10)
        terminals.close()
        if mode == "edge":
            wait_observations(cloud.service, sum(c.observations for c in terminals.counts.values()))
        settle(cloud.service)
        storage = cloud.service.storage
        rows = [r for p in plans for r in storage.estimates(p.vehicle_id, limit=100_000)]
        report = DemoReport(
            url=cloud.url,
            dashboard_url=dashboard,
            log_path=str(data_dir / "cloud.log"),
            transport="mqtt" if mqtt_url else "http",
            vehicles=len(plans),
            samples_sent=result.samples,
            telemetry_stored=storage.counts()["telemetry"],
            estimates_stored=len(rows),
            excited_share=sum(r["excited"] for r in rows) / max(1, len(rows)),
            stream_wall_s=result.wall_s,
            mode=mode,
            observations_stored=len(storage.observations_since(0)),
            heartbeats_stored=len(storage.latest_heartbeats()),
            warnings=[_where(w["message"]["event"], network) for w in storage.warnings(active_only=False)],
            patches=[
                {
                    "name": p.name,
                    "surface": p.surface,
                    "mu": p.mu,
                    "east_m": p.east_m,
                    "north_m": p.north_m,
                    "radius_m": p.radius_m,
                }
                for p in network.patches
            ],
        )
    except BaseException:
        cloud.stop()
        raise
    return report, cloud


def _log_to(path: Path) -> None:
    """The cloud's log (warnings raised, rejections, ...) goes to a file: the terminal shows the summary."""
    handler = logging.FileHandler(path)
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    logger = logging.getLogger("roadgrip")
    logger.handlers = [handler]
    logger.setLevel(logging.INFO)
    logger.propagate = False


def _where(event: dict, network: Network) -> dict:
    """The warning with the patch nearest to its cell's centre."""
    import pymap3d

    east, north, _ = pymap3d.geodetic2enu(event["latitude_deg"], event["longitude_deg"], 0.0, *network.origin, 0.0)
    nearest = min(network.patches, key=lambda p: (p.east_m - east) ** 2 + (p.north_m - north) ** 2)
    distance = float(((nearest.east_m - east) ** 2 + (nearest.north_m - north) ** 2) ** 0.5)
    return {**event, "nearest_patch": nearest.name, "patch_distance_m": distance}
