"""The `roadgrip` command line: thin commands over the package's parts."""

from __future__ import annotations

import functools
import subprocess
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

import roadgrip
from roadgrip.data.dataset import write_dataset
from roadgrip.sim.presets import PRESETS, preset_scenarios

app = typer.Typer(help="roadgrip: tire-road adhesion (mu) estimation from connected-vehicle telemetry.",
                  no_args_is_help=True, add_completion=False)
bench_app = typer.Typer(help="Performance benchmarks.", no_args_is_help=True)
app.add_typer(bench_app, name="bench")
cluster_app = typer.Typer(help="The cluster mode on one machine (docs/CLUSTER.md).", no_args_is_help=True)
app.add_typer(cluster_app, name="cluster")
console = Console()


def friendly_errors(fn):
    """Bad input ends the command with its message and exit status 2, not a traceback."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except (ValueError, TypeError, FileExistsError, FileNotFoundError) as err:
            console.print(f"[bold red]error:[/] {err}")
            raise typer.Exit(2) from err

    return wrapper


def _code_version() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=5,
                             check=False, cwd=Path(__file__).parent).stdout.strip()
    except OSError:
        sha = ""
    return f"{roadgrip.__version__}+{sha}" if sha else roadgrip.__version__


def _simulate_dataset(preset: str, runs: int | None, seed: int, out: Path, overwrite: bool,
                      scenario_file: Path | None = None):
    from roadgrip.sim.scenario_file import load_scenarios
    from roadgrip.sim.simulate import simulate

    scenarios = load_scenarios(scenario_file) if scenario_file else preset_scenarios(preset, runs, seed)
    start = time.perf_counter()
    with Progress(TextColumn("[bold]simulating[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        task = progress.add_task(f"{preset} preset", total=len(scenarios))
        table = simulate(scenarios, progress=lambda n: progress.advance(task, n))
    manifest = {
        "format": "roadgrip simulation dataset (DESIGN 3.3)",
        "preset": preset,
        "scenario_file": str(scenario_file) if scenario_file else None,
        "seed": seed,
        "runs": len(scenarios),
        "code_version": _code_version(),
        "vehicles": sorted({s.vehicle.name for s in scenarios}),
        "scenarios": [s.describe() for s in scenarios],
    }
    write_dataset(out, table, manifest, overwrite=overwrite)
    return scenarios, table, time.perf_counter() - start


@app.command()
@friendly_errors
def simulate(
    out: Path = typer.Option(..., help="output folder (Parquet + manifest)"),
    preset: str = typer.Option(None, help=f"scenario preset: {' | '.join(PRESETS)}"),
    scenario: Path = typer.Option(None, help="a scenario YAML file (see roadgrip/sim/scenario_file.py) instead of a preset"),
    runs: int = typer.Option(None, help="number of runs (random preset; the paper preset has 20)"),
    seed: int = typer.Option(0, help="seed: the same seed gives the same data"),
    overwrite: bool = typer.Option(False, help="replace an existing dataset in OUT"),
):
    """Simulate a preset (or the runs of a scenario file) and write the dataset (DESIGN 3.3)."""
    if (preset is None) == (scenario is None):
        raise ValueError("give exactly one of --preset and --scenario")
    scenarios, table, wall = _simulate_dataset(preset or "custom", runs, seed, out, overwrite, scenario)
    console.print(f"wrote {table.num_rows} samples of {len(scenarios)} runs to {out} in {wall:.1f} s")


def _parse_config(items: list[str] | None) -> dict:
    """KEY=VALUE pairs (values parsed as YAML: numbers, lists) into model config overrides."""
    import yaml

    overrides = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--config takes KEY=VALUE, got {item!r}")
        key, value = item.split("=", 1)
        value = yaml.safe_load(value)
        overrides[key] = tuple(value) if isinstance(value, list) else value
    return overrides


@app.command()
@friendly_errors
def train(
    model: str = typer.Option(..., help="dnn | cnn | convlstm | sa-cnn-lstm"),
    data: Path = typer.Option(..., help="a dataset folder (roadgrip simulate)"),
    out: Path = typer.Option(..., help="model file to write (.pt)"),
    features: str = typer.Option("terminal", help="feature set: paper | terminal | physics | production"),
    experiment: int = typer.Option(None, help="train on this experiment's runs only (paper preset: 1)"),
    condition: list[str] = typer.Option(None, help="train on these conditions only (repeatable)"),
    config: list[str] = typer.Option(None, help="model config override KEY=VALUE (repeatable)"),
    folds: int = typer.Option(0, help="also report K-fold cross-validation grouped by run (0: none)"),
    calibration: Path = typer.Option(None, help="a dataset of held-out runs to calibrate the 90 % intervals on "
                                                "(default: the validation blocks of the training runs)"),
    stride: int = typer.Option(1, help="keep every STRIDE-th training window"),
    batch_size: int = typer.Option(64, help="training batch size"),
    max_epochs: int = typer.Option(100, help="training epochs at most (early stopping on validation)"),
    patience: int = typer.Option(15, help="epochs without improvement before stopping"),
    seed: int = typer.Option(0, help="training seed"),
):
    """Train one model on a dataset and write its checkpoint."""
    import sys

    from roadgrip.data.dataset import read_dataset, read_manifest, vehicles_from_manifest
    from roadgrip.training.fit import block_split, calibration_of, cross_validate, fit, prepare, save_fitted, subset
    from roadgrip.training.trainer import TrainConfig

    manifest = read_manifest(data)
    table = read_dataset(data)
    vehicles = vehicles_from_manifest(manifest)
    if experiment is not None:
        table = table.filter(pc.equal(table["experiment"], experiment))
    if condition:
        table = table.filter(pc.is_in(table["condition"], value_set=pa.array(condition)))
    if table.num_rows == 0:
        raise ValueError(f"no rows left in {data} after the experiment/condition filters")
    overrides = _parse_config(config)
    prepared = prepare(table, features, vehicles=vehicles)
    if stride > 1:
        prepared = subset(prepared, np.arange(0, len(prepared.targets), stride))
    train_config = TrainConfig(max_epochs=max_epochs, batch_size=batch_size, patience=patience, seed=seed)
    cv = []
    if folds:
        with console.status(f"{folds}-fold cross-validation grouped by run..."):
            cv = cross_validate(model, prepared, folds, overrides, train_config)
        console.print(f"cross-validation RMSE per fold: {', '.join(f'{v:.4f}' for v in cv)} "
                      f"(mean {np.mean(cv):.4f}, std {np.std(cv):.4f})")
    with console.status(f"training {model} on {len(prepared.targets)} windows..."):
        train_idx, val_idx = block_split(prepared)
        fitted = fit(model, prepared, train_idx, val_idx, overrides, train_config)
    if calibration is not None:
        held_out = prepare(read_dataset(calibration), features, vehicles=vehicles_from_manifest(read_manifest(calibration)))
        fitted.interval = calibration_of(fitted, held_out)
    save_fitted(out, fitted, features, {
        "command": "roadgrip " + " ".join(sys.argv[1:]), "dataset": str(data), "preset": manifest.get("preset"),
        "data_seed": manifest.get("seed"), "code_version": _code_version(), "seed": seed, "windows": len(train_idx),
        "cv_rmse": cv})
    console.print(f"wrote {out}: validation RMSE {fitted.result.best_val_rmse:.4f} after {fitted.result.epochs_run} "
                  f"epochs; 90 % interval half-widths by excitation level "
                  f"{', '.join(f'{lo:+.3f}/{hi:+.3f}' for lo, hi in zip(fitted.interval['q_low'], fitted.interval['q_high']))}")


@app.command()
@friendly_errors
def evaluate(
    benchmark: str = typer.Option(..., help="paper | generalization | real-vehicle | fleet"),
    out: Path = typer.Option(..., help="output folder: metrics.csv, tables.md, figures"),
    data: Path = typer.Option(None, help="paper benchmark: a paper-preset dataset; default: simulate it (seed 0)"),
    seed: int = typer.Option(0, help="seed of the data and the training (fleet: the first seed)"),
    seeds: int = typer.Option(3, min=1, help="fleet benchmark: how many seeds (seed, seed + 1, ...)"),
    workers: int = typer.Option(2, help="training processes in parallel"),
    sweep: bool = typer.Option(False, help="fleet benchmark: also replay the warning engine's estimates over a grid of "
                                           "its settings: tradeoff.csv, tradeoff.png (roadgrip/evaluation/"
                                           "fleet_sweep.py)"),
):
    """Regenerate a benchmark: the paper's Tables 2-6 and Figures 4-8, the generalization benchmark, the paper's
    Table 7 (real-vehicle test) in simulation (DESIGN 4), or the fleet benchmark (a simulated fleet through the cloud
    service: warnings and map against the truth; docs/RESULTS.md)."""
    from roadgrip.validation import check_choice

    check_choice("evaluate", "benchmark", benchmark, {"paper", "generalization", "real-vehicle", "fleet"})
    start = time.perf_counter()
    if benchmark == "fleet":
        paths = _evaluate_fleet(out, seed, seeds, sweep)
    elif benchmark == "paper":
        paths = _evaluate_paper(out, data, seed, workers)
    elif benchmark == "real-vehicle":
        paths = _evaluate_real_vehicle(out, seed)
    else:
        paths = _evaluate_generalization(out, seed, workers)
    console.print(f"{benchmark} benchmark done in {time.perf_counter() - start:.0f} s: {out}")
    for name, path in paths.items():
        console.print(f"  {name}: {path}")


def _evaluate_paper(out: Path, data: Path | None, seed: int, workers: int) -> dict:
    from roadgrip.data.dataset import read_dataset
    from roadgrip.evaluation.paper import run_paper_benchmark
    from roadgrip.evaluation.report import write_report

    if data is None:
        _simulate_dataset("paper", None, seed, out / "data", overwrite=True)
        data = out / "data"
    table = read_dataset(data)
    with Progress(TextColumn("[bold]training[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        task = progress.add_task("paper benchmark", total=None)
        metrics, predictions = run_paper_benchmark(
            table, seed=seed, workers=workers, progress=lambda done, total: progress.update(task, completed=done,
                                                                                            total=total))
    return write_report(metrics, predictions, out)


def _evaluate_fleet(out: Path, seed: int, seeds: int, sweep: bool = False) -> dict:
    from roadgrip.evaluation.fleet_report import run_fleet_benchmark
    from roadgrip.evaluation.fleet_sweep import GRID

    with Progress(TextColumn("[bold]fleet[/] {task.description}"), BarColumn(), TimeElapsedColumn(), console=console,
                  transient=True) as progress:
        task = progress.add_task("starting", total=1.0)
        result = run_fleet_benchmark(out, seed, seeds, progress=lambda message, fraction: progress.update(
            task, completed=fraction, description=message), sweep=GRID if sweep else None)
    return result["paths"]


def _evaluate_real_vehicle(out: Path, seed: int) -> dict:
    from roadgrip.evaluation.real_vehicle import run_real_vehicle_benchmark

    with Progress(TextColumn("[bold]real-vehicle[/] {task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=True) as progress:
        task = progress.add_task("starting", total=None)
        result = run_real_vehicle_benchmark(out, seed, progress=lambda done, total, message: progress.update(
            task, completed=done, total=total, description=message))
    return {k: v for k, v in result.items() if k not in ("metrics", "ratios")}


def _evaluate_generalization(out: Path, seed: int, workers: int) -> dict:
    import pyarrow as pa
    import pyarrow.csv as pacsv

    from roadgrip.evaluation.bins import bins_markdown, run_bins_benchmark
    from roadgrip.evaluation.generalization import run_generalization_benchmark
    from roadgrip.evaluation.generalization_report import write_generalization_report

    with console.status("generalization benchmark") as status:
        say = lambda message: status.update(f"generalization benchmark: {message}")
        metrics, predictions, _, _ = run_generalization_benchmark(seed=seed, workers=workers, progress=say)
        bins = run_bins_benchmark(seed=seed, progress=say)
    paths = write_generalization_report(metrics, predictions, out)
    pacsv.write_csv(pa.Table.from_pylist(bins), Path(out) / "bins.csv")
    (Path(out) / "bins.md").write_text(bins_markdown(bins))
    return paths | {"bins_csv": Path(out) / "bins.csv", "bins_md": Path(out) / "bins.md"}


@app.command()
@friendly_errors
def estimate(
    input: Path = typer.Option(..., help="telemetry file: CSV, Parquet, NDJSON or JSON (wire format v1)"),
    out: Path = typer.Option(..., help="estimates file (.csv, .parquet or .ndjson)"),
    model: str = typer.Option("pmf", help="model file (.pt) or name: pmf (the default: docs/ESTIMATORS.md) | "
                                          "default (the shipped learned model) | ekf | ukf"),
    vehicle: Path = typer.Option(None, help="vehicle profile YAML (DESIGN 3.2); default: the paper's SUV"),
):
    """Offline estimates of mu (DESIGN 3.4) for every sample of a telemetry file that can be judged."""
    from roadgrip.data.tables import write_table
    from roadgrip.data.telemetry import read_telemetry
    from roadgrip.estimators.base import ESTIMATE_SCHEMA
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

    profile = VehicleParams.from_yaml(vehicle) if vehicle else PAPER_SUV
    estimator = load_estimator(model)
    batch = read_telemetry(input, wheel_radius_m=profile.wheel_radius_m if vehicle else None)
    for warning in batch.warnings:
        console.print(f"[yellow]warning:[/] {warning}")
    ids = np.asarray(batch.table["vehicle_id"].to_pylist())
    results = []
    for vid in dict.fromkeys(ids.tolist()):
        rows = np.flatnonzero(ids == vid)
        results.append(estimator.estimate_batch(batch.table.take(rows), batch.segments[rows], profile))
    estimates = pa.concat_tables(results) if results else ESTIMATE_SCHEMA.empty_table()
    if batch.time_column == "t_s":  # DESIGN 3.4: the timestamp as the input had it
        t_s = pc.divide(pc.cast(estimates["timestamp_ms"], pa.float64()), 1000.0)
        estimates = estimates.set_column(estimates.schema.get_field_index("timestamp_ms"), "t_s", t_s)
    write_table(estimates, out)
    console.print(f"wrote {estimates.num_rows} estimates for {batch.table.num_rows} accepted samples of "
                  f"{len(set(ids.tolist()))} vehicle(s) to {out} ({estimator.name})")
    if batch.rejections:
        report = out.with_name(out.stem + ".rejections.csv")
        write_table(batch.rejection_table(), report)
        console.print(f"[yellow]{len(batch.rejections)} input row(s) rejected:[/] see {report}")


@app.command()
@friendly_errors
def fleet(
    url: str = typer.Option("http://127.0.0.1:8000", help="the running cloud (roadgrip serve)"),
    admin_secret_file: Path = typer.Option(Path("roadgrip-data/admin-secret"),
                                           help="the cloud's admin secret (or ROADGRIP_ADMIN_SECRET)"),
    vehicles: int = typer.Option(10, min=1, help="simulated vehicles"),
    transport: str = typer.Option("auto", help="auto (MQTT when the cloud has a broker) | mqtt | http"),
    speed: float = typer.Option(1.0, min=0.01, help="times real time"),
    duration: float = typer.Option(120.0, min=1.0, help="simulated seconds of driving"),
    seed: int = typer.Option(0, help="seed of the plan and the sensors"),
    network_file: Path | None = typer.Option(None, "--network", help="roads and patches as GeoJSON (default: the "
                                                                     "generated network around the Hebei origin)"),
    per_slippery_patch: int = typer.Option(0, min=0, help="vehicles sent to brake on each slippery patch first"),
    prefix: str = typer.Option("fleet", help="vehicle ids are PREFIX-000, PREFIX-001, ..."),
    replay_log: Path | None = typer.Option(None, "--replay", help="replay a recorded log instead of simulating"),
    importer: str | None = typer.Option(None, help="importer of the log (default: detected)"),
    vehicle: str | None = typer.Option(None, help="profile of the replayed vehicle: a known name or a YAML file "
                                                  "(default: the importer's own, else paper-suv)"),
    mqtt_urls: list[str] | None = typer.Option(None, "--mqtt", help="broker to send to instead of the one the "
                                                                   "registration names (repeatable: vehicles are "
                                                                   "spread over them, e.g. a cluster's nodes)"),
    mqtt_protocol: str = typer.Option("auto", help="auto (MQTT 5, else 3.1.1 when the broker does not take 5: "
                                                   "RabbitMQ 3.10) | 5 | 3.1.1"),
    read_url: str | None = typer.Option(None, help="after the drive, read each vehicle's estimates and the map back "
                                                   "from this cloud (e.g. another API replica of a cluster)"),
):
    """Drive simulated vehicles (or replay a log) against a running cloud: each vehicle registers, then sends its
    telemetry at 10 Hz with its own credentials."""
    import math
    import os

    from roadgrip.fleet.fleet import plan_fleet, simulate_fleet, timeline
    from roadgrip.fleet.network import generated_network, network_from_geojson
    from roadgrip.fleet.replay import replay
    from roadgrip.fleet.transport import HttpTerminals, MqttTerminals, read_back, register_fleet

    if transport not in ("auto", "mqtt", "http"):
        raise ValueError(f"--transport must be auto, mqtt or http, got {transport!r}")
    if mqtt_protocol not in ("auto", "5", "3.1.1"):
        raise ValueError(f"--mqtt-protocol must be auto, 5 or 3.1.1, got {mqtt_protocol!r}")
    secret = os.environ.get("ROADGRIP_ADMIN_SECRET") or (admin_secret_file.read_text().strip()
                                                          if admin_secret_file.is_file() else None)
    if not secret:
        raise ValueError(f"no admin secret: set ROADGRIP_ADMIN_SECRET or give --admin-secret-file "
                         f"({admin_secret_file} does not exist)")
    if replay_log is not None:
        samples, profiles = _replay_samples(replay_log, importer, vehicle, prefix)
    else:
        network = network_from_geojson(network_file) if network_file else generated_network()
        with console.status(f"simulating {vehicles} vehicles..."):
            plans = plan_fleet(network, vehicles, duration_s=duration, seed=seed,
                               per_slippery_patch=per_slippery_patch, prefix=prefix)
            samples = simulate_fleet(plans, network)
        profiles = {p.vehicle_id: p.vehicle.name for p in plans}
    secrets, mqtt_url = register_fleet(url, secret, list(profiles.items()))
    brokers = mqtt_urls or ([mqtt_url] if mqtt_url is not None else [])
    use_mqtt = transport == "mqtt" or (transport == "auto" and bool(brokers))
    if use_mqtt and not brokers:
        raise ValueError("--transport mqtt, but the cloud runs without a broker (and no --mqtt was given)")
    terminals = MqttTerminals(brokers, secrets, mqtt_protocol) if use_mqtt else HttpTerminals(url, secrets)
    total = sum(len(run) for run in samples.values())
    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as bar:
        task = bar.add_task(f"{len(samples)} vehicles over {'MQTT' if use_mqtt else 'HTTP'} at {speed:g}x "
                            "(samples)", total=total)

        def send(batch: list[dict]) -> None:
            terminals.send(batch[0]["vehicle_id"], batch)
            bar.advance(task, len(batch))
        result = replay(timeline(samples, speed, time.time()), send, speed=speed if speed < 1e6 else math.inf,
                        batch=1 if use_mqtt else 10)
        terminals.close()
    acknowledged = terminals.acknowledged if use_mqtt else terminals.stored
    over = f" over MQTT {terminals.protocol} to {len(brokers)} broker(s)" if use_mqtt else ""
    console.print(f"sent {result.samples:,} samples in {result.batches:,} messages over {result.wall_s:.1f} s "
                  f"({result.late_batches} late){over}; {'acknowledged' if use_mqtt else 'stored'}: {acknowledged:,}")
    if read_url is not None:
        with console.status(f"reading the estimates and the map back from {read_url}..."):
            stored = read_back(read_url, secret, list(samples))
        counts = stored["estimates"]
        console.print(f"read back from {read_url}: {sum(counts.values()):,} estimates of "
                      f"{sum(1 for n in counts.values() if n)} of {len(counts)} vehicles, {stored['map_cells']} map "
                      f"cells ({'settled' if stored['settled'] else 'still growing'} after {stored['wait_s']:.0f} s)")


def _replay_samples(log: Path, importer: str | None, vehicle: str | None,
                    prefix: str) -> tuple[dict[str, list[dict]], dict[str, object]]:
    """The log's samples per vehicle (timestamps from 0) and each vehicle's profile (a name or a mapping)."""
    from roadgrip.fleet.importers import resolve_importer
    from roadgrip.fleet.replay import replay_file
    from roadgrip.vehicle.params import VehicleParams

    chosen = resolve_importer(log, importer)
    rows = replay_file(log, chosen, start_ms=0)
    samples: dict[str, list[dict]] = {}
    for row in rows:
        samples.setdefault(f"{prefix}-{row['vehicle_id']}", []).append({**row, "vehicle_id": f"{prefix}-"
                                                                                          f"{row['vehicle_id']}"})
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


@app.command("import-log")
@friendly_errors
def import_log(
    input: Path = typer.Argument(..., help="a recorded log: a file or folder that an importer recognises"),
    out: Path = typer.Option(..., help="wire-format telemetry file to write (.csv, .parquet, .ndjson or .jsonl)"),
    importer: str = typer.Option(None, help="importer name (default: the one that recognises INPUT): "
                                            "wire | bmw-m8 | can-dbc | any installed through entry points"),
    vehicle_id: str = typer.Option(None, help="vehicle_id of the samples (default: the importer's)"),
    start_ms: int = typer.Option(None, help="timestamp of the first sample, ms since the Unix epoch (default: the "
                                            "importer's)"),
):
    """Import a recorded log into wire format v1 (DESIGN 3.1), ready for `roadgrip estimate` or a replay."""
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
    console.print(f"wrote {table.num_rows} samples of {len(vehicles)} vehicle(s) ({', '.join(vehicles[:5])}), "
                  f"{(ts.max() - ts.min()) / 1000:.1f} s, to {out} (importer {chosen.name})")
    for key, value in (table.schema.metadata or {}).items():
        if key.startswith(b"roadgrip.") and key != b"roadgrip.importer":
            console.print(f"  {key.decode()[len('roadgrip.'):]}: {value.decode()}")


@app.command()
@friendly_errors
def serve(
    config: Path | None = typer.Option(None, help="settings file (YAML); environment variables ROADGRIP_* override it"),
    host: str | None = typer.Option(None, help="HTTP listen address (default 127.0.0.1)"),
    port: int | None = typer.Option(None, help="HTTP port (default 8000)"),
    database_url: str | None = typer.Option(None, help="sqlite:///FILE or postgresql://... (default: SQLite in "
                                                       "--data-dir)"),
    mqtt: str | None = typer.Option(None, help="off | auto (start Mosquitto when installed) | managed | mqtt://host:port"),
    data_dir: Path | None = typer.Option(None, help="folder for the database, broker files and the admin secret"),
    estimator: str | None = typer.Option(None, help="pmf (default), ekf, ukf, default (learned) or a model file"),
    ingest_processes: int | None = typer.Option(None, min=0, help="processes that ingest, estimate and store, each "
                                                                  "for its share of the vehicles (default 0: this "
                                                                  "process; 2 kept up with 1,000 vehicles at 10 Hz "
                                                                  "here, docs/RELIABILITY.md)"),
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

    settings = load_settings(config, host=host, port=port, database_url=database_url, mqtt=mqtt, data_dir=data_dir,
                             estimator=estimator, ingest_processes=ingest_processes)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    # uvicorn answers SIGTERM by shutting down and raising it again with the default action, which would end the
    # process before `service.stop()` (the last reorder windows, MQTT and storage closed): exit through Python instead
    signal.signal(signal.SIGTERM, lambda signum, _frame: sys.exit(128 + signum))
    service = CloudService(settings)
    service.start()
    tune_memory_for_serving()
    try:
        console.print(f"roadgrip cloud: http://{settings.host}:{settings.port}/docs  storage {service.storage}  "
                      f"mqtt {service.mqtt_url or 'off'}")
        console.print(f"dashboard: http://{settings.host}:{settings.port}/dashboard (log in as a reader: "
                      "POST /v1/readers with the admin secret)")
        console.print(f"admin secret: {settings.data_dir / 'admin-secret'}" if settings.admin_secret is None
                      else "admin secret: from the settings")
        uvicorn.run(create_app(service), host=settings.host, port=settings.port, log_level="warning")
    finally:
        service.stop()


@app.command()
@friendly_errors
def worker(
    broker: list[str] = typer.Option(..., help="AMQP URL of a RabbitMQ node, amqp://user:password@host:port/%2F "
                                               "(repeatable: partition p connects to the (p mod count)-th, the next "
                                               "one after a failure)"),
    database: str = typer.Option(..., help="postgresql://... shared by every worker"),
    partitions: int = typer.Option(..., min=1, help="partition queues rg.telemetry.p0..pN-1 (the same N everywhere)"),
    prefetch: int = typer.Option(100, min=1, help="unacknowledged messages per partition"),
    config: Path | None = typer.Option(None, help="settings file (YAML; the estimator, ingest and pipeline settings "
                                                  "of `serve` apply); environment variables ROADGRIP_* override it"),
    estimator: str | None = typer.Option(None, help="pmf (default), ekf, ukf, default (learned) or a model file"),
    metrics_port: int | None = typer.Option(None, min=0, max=65535, help="serve Prometheus metrics at "
                                            "http://METRICS_HOST:PORT/metrics (0: a free port, logged)"),
    metrics_host: str = typer.Option("127.0.0.1", help="address the metrics listen on (0.0.0.0: every interface)"),
):
    """A cluster worker: consumes the partition queues of RabbitMQ (single active consumer per queue), estimates
    and stores in PostgreSQL, acknowledges after storing (docs/CLUSTER.md, "Workers")."""
    import logging
    import signal
    import threading

    from roadgrip.cloud.cluster.worker import run_worker
    from roadgrip.cloud.settings import load_settings

    settings = load_settings(config, database_url=database, estimator=estimator)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    stop = threading.Event()
    for signum in (signal.SIGTERM, signal.SIGINT):
        signal.signal(signum, lambda _signum, _frame: stop.set())
    run_worker(broker, settings, partitions, prefetch, stop, metrics_port, metrics_host)


@app.command()
@friendly_errors
def api(
    database: str = typer.Option(..., help="postgresql://... shared by every replica and worker"),
    broker: list[str] = typer.Option(..., help="AMQP URL of a RabbitMQ node, amqp://user:password@host:port/%2F "
                                               "(repeatable: telemetry is published through them, the next one "
                                               "after a failure)"),
    management: list[str] = typer.Option(..., help="RabbitMQ management API of a node, http://host:15672 or "
                                                   "http://user:password@host:15672 (repeatable; without a login, "
                                                   "the first --broker's): vehicles' broker users"),
    host: str | None = typer.Option(None, help="HTTP listen address (default 127.0.0.1)"),
    port: int | None = typer.Option(None, help="HTTP port (default 8000)"),
    mqtt: str | None = typer.Option(None, help="mqtt://host:port that registered vehicles are told to connect to "
                                               "(the broker nodes' load balancer); default: none"),
    config: Path | None = typer.Option(None, help="settings file (YAML; admin_secret, payload limits, rate limit, "
                                                  "map settings of `serve` apply); environment variables ROADGRIP_* "
                                                  "override it"),
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
        console.print(f"roadgrip api: http://{settings.host}:{settings.port}/docs  storage {backend.storage}  "
                      f"brokers {len(broker)}  mqtt for vehicles {backend.mqtt_url or 'none'}")
        uvicorn.run(create_app(backend), host=settings.host, port=settings.port, log_level="warning")
    finally:
        backend.stop()


@bench_app.command("estimate")
@friendly_errors
def bench_estimate_command(
    estimators: list[str] = typer.Option(["pmf", "ekf", "ukf", "default"], "--estimator", help="estimators (repeatable)"),
    updates: int = typer.Option(20000, help="streamed updates per estimator"),
):
    """Vehicle updates per second per core and per-update latency of each estimator, streaming one sample at a time."""
    from roadgrip.bench.estimate import bench_estimators, format_bench
    from roadgrip.bench.sim import machine_description

    with console.status("benchmarking the estimators..."):
        rows = bench_estimators(tuple(estimators), updates)
    console.print(format_bench(rows))
    console.print(f"machine: {machine_description()}")


@bench_app.command("ingest")
@friendly_errors
def bench_ingest_command(
    vehicles: int = typer.Option(1000, min=1, help="simulated vehicles, each sending at 10 Hz"),
    seconds: float = typer.Option(30.0, min=1.0, help="duration of each case"),
    transport: list[str] = typer.Option(["mqtt", "http"], help="mqtt and/or http (repeatable)"),
    http_batch: int = typer.Option(10, min=1, help="samples per HTTP request (10: a terminal posting once a second)"),
    mqtt_batch: int = typer.Option(1, min=1, help="samples per MQTT message (1: every 100 ms)"),
    database_url: str | None = typer.Option(None, help="PostgreSQL URL (default: SQLite in a scratch folder)"),
    ingest_processes: int = typer.Option(0, min=0, help="the service's ingest processes (0: ingest in the service's "
                                                        "own process; docs/CLOUD.md)"),
    out: Path | None = typer.Option(None, help="write the results as JSON here"),
):
    """Vehicles at 10 Hz end to end (ingest, estimate, stored) over MQTT and HTTP, counting what was sent,
    acknowledged and stored; beside it the broker and the database alone, measured in the same run."""
    import json

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
        case = IngestCase(t, vehicles, seconds, mqtt_batch if t == "mqtt" else http_batch,
                          ingest_processes=ingest_processes)
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
        console.print(f"results: {out}; memory, backlog and latency over time: "
                      f"{plot_timelines(rows, out.with_suffix('.png'))}")


@bench_app.command("cluster")
@friendly_errors
def bench_cluster_command(
    vehicles: int = typer.Option(500, min=1, help="simulated vehicles, each its own MQTT 3.1.1 connection"),
    seconds: float = typer.Option(20.0, min=1.0, help="measuring window of each case"),
    workers: str = typer.Option("1,2,4", help="worker counts to measure, comma-separated"),
    partitions: int = typer.Option(8, min=1, help="partition queues"),
    rate: float = typer.Option(1.0, min=0.0, help="messages of 10 samples a second per vehicle in the worker cases "
                                                  "(1: a terminal; 0: as fast as PUBACKs allow)"),
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
    bench = ClusterBench(vehicles, seconds, counts, partitions, rate)
    with Progress(TextColumn("{task.description}"), BarColumn(), TimeElapsedColumn(), console=console) as bar:
        task = bar.add_task("starting", total=1.0)
        result = run_cluster_bench(bench, lambda message, fraction: bar.update(
            task, description=message, **({} if fraction is None else {"completed": fraction})))
    console.print(format_cluster_bench(result))
    console.print(f"machine: {result['machine']}; {result['elapsed_s']:.0f} s in all")
    if out is not None:
        write_json(result, out)
        console.print(f"results: {out}")


@bench_app.command("sim")
@friendly_errors
def bench_sim_command(
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
        table.add_row(row["case"], str(row["runs"]), f"{row['simulated_s']:.0f}", f"{row['wall_s']:.3f}",
                      f"{row['realtime_factor']:,.0f}")
    console.print(table)
    console.print(f"machine: {machine_description()}")


@app.command()
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
):
    """The main job end to end: start the cloud (and a broker when Mosquitto is installed), drive a small fleet over a
    road network with icy, snowy and wet patches, and summarise the estimates and warnings the cloud produced."""
    from roadgrip.fleet.demo import run_demo

    with Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                  console=console) as bar:
        task = bar.add_task("simulating the fleet and starting the cloud", total=None)

        def ready(url: str, dashboard: str) -> None:
            bar.console.print(f"cloud: {url}/docs   dashboard: {dashboard}")
            bar.update(task, description=f"{vehicles} vehicles driving at {speed:g}x real time (samples)")

        report, cloud = run_demo(vehicles=vehicles, speed=speed, duration_s=duration, seed=seed, data_dir=data_dir,
                                 port=port, mqtt=mqtt, on_ready=ready,
                                 progress=lambda done, total: bar.update(task, completed=done, total=total))
    try:
        summary = Table(title=f"roadgrip demo: {report.vehicles} vehicles over {report.transport.upper()}")
        summary.add_column("what")
        summary.add_column("value", justify="right")
        for name, value in (("samples sent", f"{report.samples_sent:,}"),
                            ("telemetry stored", f"{report.telemetry_stored:,}"),
                            ("estimates stored", f"{report.estimates_stored:,}"),
                            ("share judged excited", f"{report.excited_share:.0%}"),
                            ("streaming wall time", f"{report.stream_wall_s:.1f} s")):
            summary.add_row(name, value)
        console.print(summary)
        warnings = Table(title=f"slippery-road warnings ({len(report.warnings)})")
        for name in ("cell", "status", "reason", "latitude", "longitude", "evidence mu_upper", "passes", "vehicles",
                     "nearest patch"):
            warnings.add_column(name, justify="left" if name in ("cell", "status", "reason", "nearest patch")
                                else "right")
        for w in report.warnings:
            warnings.add_row(w["cell"], w["status"], w["reason"], f"{w['latitude_deg']:.5f}",
                             f"{w['longitude_deg']:.5f}", f"{w['mu_upper']:.2f}", str(w["n_passes"]),
                             str(w["n_vehicles"]), f"{w['nearest_patch']} ({w['patch_distance_m']:.0f} m)")
        console.print(warnings)
        console.print("patches: " + ", ".join(f"{p['name']} (mu {p['mu']:.2f}, {p['radius_m']:.0f} m)"
                                              for p in report.patches))
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


@cluster_app.command("up")
@friendly_errors
def cluster_up(
    data_dir: Path | None = typer.Option(None, help="new or empty folder for the cluster's databases, logs and "
                                                    "secrets (default: a new temporary folder)"),
    nodes: int = typer.Option(3, min=1, help="RabbitMQ nodes joined into one cluster (quorum queues: 3 survive "
                                             "the loss of one)"),
    workers: int = typer.Option(2, min=0, help="`roadgrip worker` processes"),
    apis: int = typer.Option(2, min=0, help="`roadgrip api` replicas"),
    partitions: int = typer.Option(4, min=1, help="partition queues of the vehicles' telemetry"),
    api_port: int = typer.Option(0, min=0, max=65535, help="HTTP port of the first API replica, the others on the "
                                                           "next ports (0: free ports)"),
    config: Path | None = typer.Option(None, help="settings file (YAML) for every worker and API replica; "
                                                  "environment variables ROADGRIP_* apply too"),
):
    """A local cluster on 127.0.0.1: RabbitMQ nodes joined into one cluster, PostgreSQL, workers and API replicas,
    each waited for until healthy; runs until Ctrl-C or SIGTERM, then stops everything it started."""
    import logging
    import signal
    import tempfile

    from roadgrip.cloud.cluster.local import ClusterError, LocalCluster

    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    data_dir = data_dir or Path(tempfile.mkdtemp(prefix="roadgrip-cluster-"))
    cluster = LocalCluster(data_dir, nodes=nodes, workers=workers, apis=apis, partitions=partitions,
                           api_port=api_port, config=config)

    def interrupt(signum, _frame):
        raise KeyboardInterrupt(signal.Signals(signum).name)

    signal.signal(signal.SIGTERM, interrupt)  # SIGINT (Ctrl-C) raises KeyboardInterrupt already
    try:
        with console.status("starting the local cluster") as status:
            cluster.start(progress=lambda step: status.update(f"starting the local cluster: {step}..."))
        _print_cluster(cluster)
        reported: set[str] = set()
        while True:
            time.sleep(1.0)
            for child in cluster.exited():
                if child.name not in reported:
                    reported.add(child.name)
                    console.print(f"[bold red]{child.name} exited[/] with status {child.returncode}: see "
                                  f"{child.log_path}")
            for node in cluster.nodes_down():
                if f"node {node}" not in reported:
                    reported.add(f"node {node}")
                    console.print(f"[bold red]RabbitMQ node {cluster.rabbit.node_name(node)} exited[/]: see "
                                  f"{cluster.data_dir / 'rabbitmq' / f'rg{node}'}")
    except KeyboardInterrupt:
        pass
    except ClusterError as err:
        console.print(f"[bold red]error:[/] {err}")
        raise typer.Exit(1) from err
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut the stop short
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        with console.status("stopping the local cluster (the workers store what they took)..."):
            cluster.stop()
        console.print(f"local cluster stopped; its data and logs stay in {cluster.data_dir}")


def _print_cluster(cluster) -> None:
    """What runs where, and the ready line."""
    d = cluster.describe()
    table = Table(title=f"roadgrip local cluster in {d['data_dir']}")
    for name in ("process", "where", "pid", "log"):
        table.add_column(name)
    for node in d["rabbitmq"]:
        table.add_row(f"RabbitMQ {node['node']}", f"{node['mqtt']}  {node['amqp']}  {node['management']}",
                      str(node["pid"]), node["log"])
    table.add_row("PostgreSQL", d["postgres"]["url"], str(d["postgres"]["pid"]), d["postgres"]["log"])
    for child in d["workers"]:
        table.add_row(child["name"], f"{d['partitions']} partitions, {child['metrics']}", str(child["pid"]),
                      child["log"])
    for child in d["apis"]:
        table.add_row(child["name"], f"{child['url']}/docs", str(child["pid"]), child["log"])
    console.print(table)
    console.print(f"admin secret: {d['admin_secret_file']}   broker user svc's secret: {d['broker_secret_file']}")
    if d["fleet_command"]:
        console.print(f"drive a fleet against it: {d['fleet_command']}")
    console.print(f"[bold green]local cluster ready[/] in {cluster.started_s:.0f} s ({d['data_dir']}/cluster.json); "
                  "Ctrl-C stops it")
