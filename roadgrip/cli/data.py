"""The offline commands: `roadgrip simulate`, `train`, `evaluate` and `estimate` (datasets, models, benchmarks and
estimates from files), and the dataset manifest they write."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

import roadgrip
from roadgrip.cli.common import console, friendly_errors
from roadgrip.data.dataset import write_dataset
from roadgrip.sim.presets import PRESETS, preset_scenarios


def _code_version() -> str:
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"],
            capture_output=True,
            text=True,
            timeout=5,
            check=False,
            cwd=Path(__file__).parent,
        ).stdout.strip()
    except OSError:
        sha = ""
    return f"{roadgrip.__version__}+{sha}" if sha else roadgrip.__version__


def _simulate_dataset(
    preset: str, runs: int | None, seed: int, out: Path, overwrite: bool, scenario_file: Path | None = None
):
    from roadgrip.sim.scenario_file import load_scenarios
    from roadgrip.sim.simulate import simulate

    scenarios = load_scenarios(scenario_file) if scenario_file else preset_scenarios(preset, runs, seed)
    start = time.perf_counter()
    with Progress(
        TextColumn("[bold]simulating[/] {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        task = progress.add_task(f"{preset} preset", total=len(scenarios))
        table = simulate(scenarios, progress=lambda n: progress.advance(task, n))
    manifest = {
        "format": "roadgrip simulation dataset (CONTRACTS 3.3)",
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


@friendly_errors
def simulate(
    out: Path = typer.Option(..., help="output folder (Parquet + manifest)"),
    preset: str = typer.Option(None, help=f"scenario preset: {' | '.join(PRESETS)}"),
    scenario: Path = typer.Option(
        None, help="a scenario YAML file (see roadgrip/sim/scenario_file.py) instead of a preset"
    ),
    runs: int = typer.Option(None, help="number of runs (random preset; the paper preset has 20)"),
    seed: int = typer.Option(0, help="seed: the same seed gives the same data"),
    overwrite: bool = typer.Option(False, help="replace an existing dataset in OUT"),
):
    """Simulate a preset (or the runs of a scenario file) and write the dataset (CONTRACTS 3.3)."""
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
    calibration: Path = typer.Option(
        None,
        help="a dataset of held-out runs to calibrate the 90 % intervals on "
        "(default: the validation blocks of the training runs)",
    ),
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
        console.print(
            f"cross-validation RMSE per fold: {', '.join(f'{v:.4f}' for v in cv)} "
            f"(mean {np.mean(cv):.4f}, std {np.std(cv):.4f})"
        )
    with console.status(f"training {model} on {len(prepared.targets)} windows..."):
        train_idx, val_idx = block_split(prepared)
        fitted = fit(model, prepared, train_idx, val_idx, overrides, train_config)
    if calibration is not None:
        held_out = prepare(
            read_dataset(calibration), features, vehicles=vehicles_from_manifest(read_manifest(calibration))
        )
        fitted.interval = calibration_of(fitted, held_out)
    save_fitted(
        out,
        fitted,
        features,
        {
            "command": "roadgrip " + " ".join(sys.argv[1:]),
            "dataset": str(data),
            "preset": manifest.get("preset"),
            "data_seed": manifest.get("seed"),
            "code_version": _code_version(),
            "seed": seed,
            "windows": len(train_idx),
            "cv_rmse": cv,
        },
    )
    console.print(
        f"wrote {out}: validation RMSE {fitted.result.best_val_rmse:.4f} after {fitted.result.epochs_run} "
        f"epochs; 90 % interval half-widths by excitation level "
        f"{', '.join(f'{lo:+.3f}/{hi:+.3f}' for lo, hi in zip(fitted.interval['q_low'], fitted.interval['q_high']))}"
    )


@friendly_errors
def evaluate(
    benchmark: str = typer.Option(..., help="paper | generalization | real-vehicle | fleet | physics"),
    out: Path = typer.Option(..., help="output folder: metrics.csv, tables.md, figures"),
    data: Path = typer.Option(None, help="paper benchmark: a paper-preset dataset; default: simulate it (seed 0)"),
    seed: int = typer.Option(0, help="seed of the data and the training (fleet: the first seed)"),
    seeds: int = typer.Option(3, min=1, help="fleet benchmark: how many seeds (seed, seed + 1, ...)"),
    workers: int = typer.Option(2, help="training processes in parallel"),
    sweep: bool = typer.Option(
        False,
        help="fleet benchmark: also replay the warning engine's estimates over a grid of "
        "its settings: tradeoff.csv, tradeoff.png (roadgrip/evaluation/"
        "fleet_sweep.py)",
    ),
    mode: str = typer.Option(
        "raw",
        help="fleet benchmark: the vehicles send raw telemetry (raw) or friction observations made on board (edge, "
        "docs/EDGE.md)",
    ),
    channel_share: float = typer.Option(
        0.0,
        min=0.0,
        max=1.0,
        help="fleet benchmark: share of the vehicles that send every optional channel (GNSS speed, forces, steering "
        "torques; CONTRACTS 3.1)",
    ),
    split: str = typer.Option(
        "validation",
        help="physics benchmark: validation (choose constants here) | test (held out: run once per release of the "
        "numbers; printed only when asked for by name)",
    ),
    channels: str = typer.Option(
        "",
        help="physics benchmark: comma-separated channel sets, each run with every optional channel the set lacks "
        "blanked: base | gnss | forces | steering | all | gnss-degraded (default: none, the benchmark without them)",
    ),
    estimator: list[str] = typer.Option(
        [], "--estimator", help="physics benchmark: estimators beside the prior (repeatable; default: all four)"
    ),
    runs: int = typer.Option(0, min=0, help="physics benchmark: the split's first runs only (0: all 240)"),
    lead_in_s: float = typer.Option(
        0.0,
        min=0.0,
        help="physics benchmark: each estimator first reads this long a calm drive of the same car, a new trip "
        "before each run (a fleet car's calibration); 0: each car seen for the first time",
    ),
):
    """Regenerate a benchmark: the paper's Tables 2-6 and Figures 4-8, the generalization benchmark, the paper's
    Table 7 (real-vehicle test) in simulation (CONTRACTS 4), or the fleet benchmark (a simulated fleet through the cloud
    service: warnings and map against the truth; docs/RESULTS.md), or the physics benchmark (every estimator beside the
    prior baseline, mu 0.1-1.2, by utilization bin and mu band; docs/RESULTS.md)."""
    from roadgrip.validation import check_choice

    check_choice("evaluate", "benchmark", benchmark, {"paper", "generalization", "real-vehicle", "fleet", "physics"})
    start = time.perf_counter()
    if benchmark == "physics":
        paths = _evaluate_physics(out, split, seed, channels, tuple(estimator), runs, lead_in_s)
    elif benchmark == "fleet":
        check_choice("evaluate", "mode", mode, {"raw", "edge"})
        paths = _evaluate_fleet(out, seed, seeds, sweep, mode, channel_share)
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
    with Progress(
        TextColumn("[bold]training[/] {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        task = progress.add_task("paper benchmark", total=None)
        metrics, predictions = run_paper_benchmark(
            table,
            seed=seed,
            workers=workers,
            progress=lambda done, total: progress.update(task, completed=done, total=total),
        )
    return write_report(metrics, predictions, out)


def _evaluate_fleet(
    out: Path, seed: int, seeds: int, sweep: bool = False, mode: str = "raw", channel_share: float = 0.0
) -> dict:
    from roadgrip.evaluation.fleet_benchmark import FleetConfig
    from roadgrip.evaluation.fleet_report import run_fleet_benchmark
    from roadgrip.evaluation.fleet_sweep import GRID

    with Progress(
        TextColumn("[bold]fleet[/] {task.description}"),
        BarColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        task = progress.add_task("starting", total=1.0)
        result = run_fleet_benchmark(
            out,
            seed,
            seeds,
            config=FleetConfig(channel_share=channel_share),
            progress=lambda message, fraction: progress.update(task, completed=fraction, description=message),
            sweep=GRID if sweep else None,
            mode=mode,
        )
    return result["paths"]


def _evaluate_real_vehicle(out: Path, seed: int) -> dict:
    from roadgrip.evaluation.real_vehicle import run_real_vehicle_benchmark

    with Progress(
        TextColumn("[bold]real-vehicle[/] {task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        task = progress.add_task("starting", total=None)
        result = run_real_vehicle_benchmark(
            out,
            seed,
            progress=lambda done, total, message: progress.update(
                task, completed=done, total=total, description=message
            ),
        )
    return {k: v for k, v in result.items() if k not in ("metrics", "ratios")}


def _evaluate_physics(
    out: Path,
    split: str,
    seed: int,
    channels: str = "",
    estimators: tuple[str, ...] = (),
    runs: int = 0,
    lead_in_s: float = 0.0,
) -> dict:
    import pyarrow.csv as pacsv

    from roadgrip.evaluation.bins import BIN_ESTIMATORS
    from roadgrip.evaluation.physics_benchmark import physics_markdown, rows_table, run_physics_benchmark
    from roadgrip.validation import check_choice

    check_choice("evaluate", "split", split, {"validation", "test"})
    if seed != 0:
        raise ValueError(
            f"the physics benchmark's seeds are fixed per split (roadgrip/sim/presets.py), got --seed {seed}"
        )
    with console.status(f"physics benchmark, {split} split") as status:
        rows = run_physics_benchmark(
            split,
            estimators or BIN_ESTIMATORS,
            runs or None,
            progress=lambda message: status.update(f"physics benchmark: {message}"),
            channels=tuple(c.strip() for c in channels.split(",") if c.strip()) or None,
            lead_in_s=lead_in_s,
        )
    out.mkdir(parents=True, exist_ok=True)
    table = physics_markdown(rows)
    stem = f"physics_{split}" + ("_channels" if channels else "") + ("_calibrated" if lead_in_s else "")
    paths = {"csv": out / f"{stem}.csv", "md": out / f"{stem}.md"}
    pacsv.write_csv(rows_table(rows), paths["csv"])
    paths["md"].write_text(table)
    console.print(f"physics benchmark, {split} split:\n{table}")
    return paths


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


@friendly_errors
def estimate(
    input: Path = typer.Option(..., help="telemetry file: CSV, Parquet, NDJSON or JSON (wire format v1)"),
    out: Path = typer.Option(..., help="estimates file (.csv, .parquet or .ndjson)"),
    model: str = typer.Option(
        "pmf",
        help="model file (.pt) or name: pmf (the default: docs/ESTIMATORS.md) | "
        "default (the shipped learned model) | ekf | ukf",
    ),
    vehicle: Path = typer.Option(None, help="vehicle profile YAML (CONTRACTS 3.2); default: the paper's SUV"),
):
    """Offline estimates of mu (CONTRACTS 3.4) for every sample of a telemetry file that can be judged."""
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
    if batch.time_column == "t_s":  # CONTRACTS 3.4: the timestamp as the input had it
        t_s = pc.divide(pc.cast(estimates["timestamp_ms"], pa.float64()), 1000.0)
        estimates = estimates.set_column(estimates.schema.get_field_index("timestamp_ms"), "t_s", t_s)
    write_table(estimates, out)
    console.print(
        f"wrote {estimates.num_rows} estimates for {batch.table.num_rows} accepted samples of "
        f"{len(set(ids.tolist()))} vehicle(s) to {out} ({estimator.name})"
    )
    if batch.rejections:
        report = out.with_name(out.stem + ".rejections.csv")
        write_table(batch.rejection_table(), report)
        console.print(f"[yellow]{len(batch.rejections)} input row(s) rejected:[/] see {report}")
