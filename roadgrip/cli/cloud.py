"""The cloud's processes: `roadgrip serve` (the embedded service), and the cluster's `worker` and `api` replicas.
Each imports the cloud inside the command, so that `roadgrip --help` stays fast."""

from __future__ import annotations

from pathlib import Path

import typer

from roadgrip.cli.common import console, friendly_errors


@friendly_errors
def serve(
    config: Path | None = typer.Option(None, help="settings file (YAML); environment variables ROADGRIP_* override it"),
    host: str | None = typer.Option(None, help="HTTP listen address (default 127.0.0.1)"),
    port: int | None = typer.Option(None, help="HTTP port (default 8000)"),
    database_url: str | None = typer.Option(
        None, help="sqlite:///FILE or postgresql://... (default: SQLite in --data-dir)"
    ),
    mqtt: str | None = typer.Option(
        None, help="off | auto (start Mosquitto when installed) | managed | mqtt://host:port"
    ),
    data_dir: Path | None = typer.Option(None, help="folder for the database, broker files and the admin secret"),
    estimator: str | None = typer.Option(None, help="pmf (default), ekf, ukf, default (learned) or a model file"),
    ingest_processes: int | None = typer.Option(
        None,
        min=0,
        help="processes that ingest, estimate and store, each "
        "for its share of the vehicles (default 0: this "
        "process; 2 kept up with 1,000 vehicles at 10 Hz "
        "here, docs/RELIABILITY.md)",
    ),
):
    """The cloud platform: HTTP (and MQTT) ingest, per-vehicle estimation, storage, friction map, warnings."""
    import logging
    import signal
    import sys

    import uvicorn

    from roadgrip.cloud.api.app import create_app
    from roadgrip.cloud.process import tune_memory_for_serving
    from roadgrip.cloud.serve.service import CloudService
    from roadgrip.cloud.settings import load_settings

    settings = load_settings(
        config,
        host=host,
        port=port,
        database_url=database_url,
        mqtt=mqtt,
        data_dir=data_dir,
        estimator=estimator,
        ingest_processes=ingest_processes,
    )
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # uvicorn answers SIGTERM by shutting down and raising it again with the default action, which would end the
    # process before `service.stop()` (the last reorder windows, MQTT and storage closed): exit through Python instead
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
    service = CloudService(settings)
    service.start()
    tune_memory_for_serving()
    try:
        console.print(
            f"roadgrip cloud: http://{settings.host}:{settings.port}/docs  storage {service.storage}  "
            f"mqtt {service.mqtt_url or 'off'}"
        )
        console.print(
            f"dashboard: http://{settings.host}:{settings.port}/dashboard (log in as a reader: "
            "POST /v1/readers with the admin secret)"
        )
        console.print(
            f"admin secret: {settings.data_dir / 'admin-secret'}"
            if settings.admin_secret is None
            else "admin secret: from the settings"
        )
        uvicorn.run(create_app(service), host=settings.host, port=settings.port, log_level="warning")
    finally:
        service.stop()


@friendly_errors
def worker(
    broker: list[str] = typer.Option(
        ...,
        help="AMQP URL of a RabbitMQ node, amqp://user:password@host:port/%2F "
        "(repeatable: partition p connects to the (p mod count)-th, the next "
        "one after a failure)",
    ),
    database: str = typer.Option(..., help="postgresql://... shared by every worker"),
    partitions: int = typer.Option(..., min=1, help="partition queues rg.telemetry.p0..pN-1 (the same N everywhere)"),
    prefetch: int | None = typer.Option(
        None, min=1, help="unacknowledged messages per partition (default: the worker's DEFAULT_PREFETCH, 500)"
    ),
    config: Path | None = typer.Option(
        None,
        help="settings file (YAML; the estimator, ingest and pipeline settings "
        "of `serve` apply); environment variables ROADGRIP_* override it",
    ),
    estimator: str | None = typer.Option(None, help="pmf (default), ekf, ukf, default (learned) or a model file"),
    metrics_port: int | None = typer.Option(
        None,
        min=0,
        max=65535,
        help="serve Prometheus metrics at http://METRICS_HOST:PORT/metrics (0: a free port, logged)",
    ),
    metrics_host: str = typer.Option("127.0.0.1", help="address the metrics listen on (0.0.0.0: every interface)"),
):
    """A cluster worker: consumes the partition queues of RabbitMQ (single active consumer per queue), estimates
    and stores in PostgreSQL, acknowledges after storing (docs/CLUSTER.md, "Workers")."""
    import logging
    import signal
    import threading

    from roadgrip.cloud.cluster.worker import DEFAULT_PREFETCH, run_worker
    from roadgrip.cloud.settings import load_settings

    settings = load_settings(config, database_url=database, estimator=estimator)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda _signum, _frame: stop.set())
    prefetch = DEFAULT_PREFETCH if prefetch is None else prefetch
    run_worker(broker, settings, partitions, prefetch, stop, metrics_port, metrics_host)


@friendly_errors
def api(
    database: str = typer.Option(..., help="postgresql://... shared by every replica and worker"),
    broker: list[str] = typer.Option(
        ...,
        help="AMQP URL of a RabbitMQ node, amqp://user:password@host:port/%2F "
        "(repeatable: telemetry is published through them, the next one "
        "after a failure)",
    ),
    management: list[str] = typer.Option(
        ...,
        help="RabbitMQ management API of a node, http://host:15672 or "
        "http://user:password@host:15672 (repeatable; without a login, "
        "the first --broker's): vehicles' broker users",
    ),
    host: str | None = typer.Option(None, help="HTTP listen address (default 127.0.0.1)"),
    port: int | None = typer.Option(None, help="HTTP port (default 8000)"),
    mqtt: str | None = typer.Option(
        None,
        help="mqtt://host:port that registered vehicles are told to connect to "
        "(the broker nodes' load balancer); default: none",
    ),
    config: Path | None = typer.Option(
        None,
        help="settings file (YAML; admin_secret, payload limits, rate limit, "
        "map settings of `serve` apply); environment variables ROADGRIP_* "
        "override it",
    ),
):
    """A stateless API replica of the cluster: run any number behind a load balancer, all on one database and
    broker (docs/CLUSTER.md, "Stateless API"). The admin secret comes from ROADGRIP_ADMIN_SECRET or --config."""
    import logging
    import signal
    import sys

    import uvicorn

    from roadgrip.cloud.api.app import create_app
    from roadgrip.cloud.cluster.api_backend import ClusterBackend
    from roadgrip.cloud.settings import load_settings

    settings = load_settings(config, database_url=database, host=host, port=port, mqtt=mqtt)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
    backend = ClusterBackend(settings, broker, management)
    backend.start()
    try:
        console.print(
            f"roadgrip api: http://{settings.host}:{settings.port}/docs  storage {backend.storage}  "
            f"brokers {len(broker)}  mqtt for vehicles {backend.mqtt_url or 'none'}"
        )
        uvicorn.run(create_app(backend), host=settings.host, port=settings.port, log_level="warning")
    finally:
        backend.stop()
