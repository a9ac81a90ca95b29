"""`roadgrip evaluate --benchmark fleet`: run the fleet benchmark (roadgrip/evaluation/fleet_benchmark.py) for several
seeds, score it (roadgrip/evaluation/fleet_metrics.py) and write DIR/metrics.csv (per seed and pooled, per band and
overall), DIR/patches.csv (one row per patch and seed), DIR/cells.csv (every map cell scored at a snapshot),
DIR/stations.csv (detection with and without the roadside stations, per seed and pooled), DIR/fleet.md,
DIR/map_vs_truth.png, DIR/detection_delay.png and the service's log DIR/cloud.log.

The headline warnings are the vehicles' alone; the stations' are reported beside them. The service runs with the
stations (fleet_benchmark.simulate_station_reports); the vehicles' warnings are the warning engine's recorded input
replayed without the stations' rounds (fleet_sweep.replay at the product's settings), since stations change no
vehicle's estimate. Replaying with the stations' rounds must give the service's own warnings back: checked per seed
(`replay_matches_service`). The map's scores are the service's (vehicles and stations).

Seeds: the report seeds (`seed`, `seeds`: 0, 1, 2 by default) are scored; the trade-off sweep of the warning engine's
settings (`sweep`) runs on other seeds, TUNING_SEEDS (100, 101, 102), so that the product's thresholds are chosen on
seeds the reported figures do not come from."""

from __future__ import annotations

import logging
import math
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.csv as pacsv
import pyarrow.parquet as pq

from roadgrip.cloud.domain.friction_map import BOUNDED, MEASURED
from roadgrip.cloud.settings import Settings
from roadgrip.evaluation.fleet_benchmark import (
    FleetConfig,
    FleetScenario,
    ServiceRun,
    find_passes,
    make_scenario,
    observable,
    patch_cells,
    run_service,
    simulate_drives,
    truth_by_cell,
)
from roadgrip.evaluation.fleet_metrics import (
    DRY_MU,
    TARGET_LINGER_S,
    PatchTruth,
    Warning,
    score_cell,
    score_warnings,
    summarize_run,
    warning_from_row,
)
from roadgrip.evaluation.fleet_sweep import as_warnings, choose, replay, rounds_of, tradeoff_markdown
from roadgrip.evaluation.fleet_sweep import sweep as run_sweep

DATA_CLOCK_LAG_S = 3600.0  # the run's data clock ends this long before the wall clock (no sample from the future)
TUNING_SEEDS = (100, 101, 102)  # the sweep's seeds: never the report's


@dataclass
class SeedResult:
    seed: int
    scenario: FleetScenario
    run: ServiceRun
    warnings: list[Warning]  # the vehicles' alone (the headline)
    kinds: list[str]
    patch_rows: list[dict]
    cell_scores: list[dict]
    rows: list[dict]  # summarize_run of the vehicles' warnings, with the service's map
    dry_km: float
    driven_cells: int
    cells_with_evidence: int  # driven cells (summed over snapshots) where the map has evidence of any kind
    cells_measured: int  # ... where it has a measurement (excited evidence or a station)
    simulate_s: float
    truth: PatchTruth
    start_ms: int
    service_warnings: list[Warning]  # the service's: vehicles and stations
    station_rows: list[dict]  # summarize_run of the service's warnings
    station_patch_rows: list[dict]
    station_kinds: list[str]
    replay_matches_service: bool


def patch_truth(scenario: FleetScenario, drives) -> PatchTruth:
    network = scenario.network
    cells = {p.name: patch_cells(network, p) for p in network.patches}
    passes, after, seen = {}, {}, {}
    for patch in network.patches:
        if patch.mu >= DRY_MU:
            continue
        passes[patch.name] = find_passes(drives.t_s, drives.vehicle, drives.east_m, drives.north_m, drives.mu, patch)
        after[patch.name] = sum(
            patch.dry_s <= p[1] < patch.dry_s + TARGET_LINGER_S
            for p in find_passes(
                drives.t_s, drives.vehicle, drives.east_m, drives.north_m, drives.mu, patch, while_there=False
            )
        )
        seen[patch.name] = observable(drives, patch, passes[patch.name])
    return PatchTruth(tuple(network.patches), cells, passes, after, seen)


def run_seed(
    seed: int, config: FleetConfig, progress: Callable[[str, float], None] | None = None, mode: str = "raw"
) -> SeedResult:
    """One seed end to end: scenario, simulation, the service (the vehicles in `mode`: raw telemetry, or edge:
    friction observations, roadgrip/evaluation/fleet_edge.py), the scores."""
    say = progress or (lambda message, fraction: None)
    say(f"seed {seed}: simulating", 0.0)
    scenario = make_scenario(seed, config)
    start_ms = int(time.time() - config.duration_s - DATA_CLOCK_LAG_S) * 1000
    started = time.perf_counter()
    drives = simulate_drives(scenario, start_ms)
    simulate_s = time.perf_counter() - started
    with tempfile.TemporaryDirectory(prefix="roadgrip-fleet-") as tmp:
        run = run_service(
            scenario,
            drives,
            Path(tmp),
            mode=mode,
            progress=lambda t: say(
                f"seed {seed}: the service at {t / 60:.0f} of {config.duration_s / 60:.0f} min", t / config.duration_s
            ),
        )
    network = scenario.network
    validity_s = Settings.model_fields["warning_validity_s"].default
    service_warnings = [warning_from_row(row, start_ms) for row in run.warnings]
    warnings = as_warnings(replay(rounds_of(run.estimates)), start_ms)  # the vehicles alone, the product's settings
    replayed = as_warnings(replay(rounds_of(run.estimates, run.stations)), start_ms)
    matches = sorted(replayed, key=lambda w: (w.detection_s, w.cell)) == sorted(
        service_warnings, key=lambda w: (w.detection_s, w.cell)
    )
    truth = patch_truth(scenario, drives)
    kinds, patch_rows = score_warnings(seed, truth, warnings, validity_s, config.duration_s)
    cell_scores, driven_total, evidence_total, measured_total = [], 0, 0, 0
    for instant, summaries in sorted(run.snapshots.items()):
        cell_truth = truth_by_cell(network, instant)
        measured = {c.cell for c in summaries if c.status == MEASURED}
        claimed = {c.cell for c in summaries if c.status in (MEASURED, BOUNDED)}
        for c in summaries:
            if c.status in (MEASURED, BOUNDED) and c.cell in cell_truth:
                cell_scores.append(
                    {
                        "seed": seed,
                        "t_s": instant,
                        "cell": c.cell,
                        "mu_upper": c.mu_upper,
                        "status": c.status,
                        **score_cell(c.mu, c.mu_lower, c.mu_upper, cell_truth[c.cell]),
                    }
                )
        window = (drives.t_s > instant - 600.0) & (drives.t_s <= instant)
        driven = set(drives.cell[window].tolist())
        driven_total += len(driven)
        evidence_total += len(driven & claimed)
        measured_total += len(driven & measured)
    dry_km = float(drives.distance_m[drives.mu >= DRY_MU].sum() / 1000.0)
    rows = [
        {"seed": str(seed), **r}
        for r in summarize_run(patch_rows, cell_scores, kinds, dry_km, driven_total, evidence_total, measured_total)
    ]
    station_kinds, station_patch_rows = score_warnings(seed, truth, service_warnings, validity_s, config.duration_s)
    at = {site.patch: site.station_id for site in run.station_sites if site.patch is not None}
    for row, served in zip(patch_rows, station_patch_rows):
        row.update(
            station=at.get(row["patch"], ""),
            detected_with_stations=served["detected"],
            time_to_first_s_with_stations=served["time_to_first_s"],
            passes_to_first_with_stations=served["passes_to_first"],
            cancelled_while_there_with_stations=served["cancelled_while_there"],
        )
    station_rows = [
        {"seed": str(seed), **r} for r in summarize_run(station_patch_rows, [], station_kinds, dry_km, 0, 0)
    ]
    return SeedResult(
        seed,
        scenario,
        run,
        warnings,
        kinds,
        patch_rows,
        cell_scores,
        rows,
        dry_km,
        driven_total,
        evidence_total,
        measured_total,
        simulate_s,
        truth,
        start_ms,
        service_warnings,
        station_rows,
        station_patch_rows,
        station_kinds,
        matches,
    )


def run_fleet_benchmark(
    out: Path,
    seed: int = 0,
    seeds: int = 3,
    config: FleetConfig = FleetConfig(),
    progress: Callable[[str, float], None] | None = None,
    sweep: dict | None = None,
    tuning_seeds: tuple[int, ...] = TUNING_SEEDS,
    mode: str = "raw",
) -> dict:
    """Every report seed (seed, seed + 1, ...), pooled scores, the files (with DIR/estimates_seed{S}.parquet: what the
    warning engine took, fleet_benchmark.EngineRecorder). `mode`: the vehicles send raw telemetry, or (edge) friction
    observations made on board (fleet_edge.py). `sweep`: a grid of warning-engine parameters
    (fleet_sweep.GRID) to replay the estimates of `tuning_seeds` with (run for that, never a report seed):
    DIR/tradeoff.csv and DIR/tradeoff.png. Returns the paths written and the metrics rows."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds!r}")
    report_seeds = range(seed, seed + seeds)
    if sweep is not None and (not tuning_seeds or set(tuning_seeds) & set(report_seeds)):
        raise ValueError(
            f"tuning_seeds must be given and apart from the report seeds {list(report_seeds)}, got {tuning_seeds!r}"
        )
    logger = logging.getLogger("roadgrip")
    handler = logging.FileHandler(out / "cloud.log", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    saved = logger.handlers, logger.level, logger.propagate
    logger.handlers, logger.propagate = [handler], False
    logger.setLevel(logging.INFO)
    started = time.perf_counter()
    try:
        results = [run_seed(s, config, progress, mode) for s in report_seeds]
        tuning = [run_seed(s, config, progress, mode) for s in tuning_seeds] if sweep is not None else []
    finally:
        logger.handlers, logger.level, logger.propagate = saved
        handler.close()
    for res in results:
        pq.write_table(res.run.estimates, out / f"estimates_seed{res.seed}.parquet")
    sweep_rows = None
    if sweep is not None:
        sweep_started = time.perf_counter()
        sweep_rows = run_sweep(tuning, config.duration_s, sweep, progress=progress)
        sweep_s = time.perf_counter() - sweep_started
    wall_s = time.perf_counter() - started
    patch_rows = [r for res in results for r in res.patch_rows]
    cell_scores = [s for res in results for s in res.cell_scores]
    pooled = [
        {"seed": "pooled", **r}
        for r in summarize_run(
            patch_rows,
            cell_scores,
            [k for res in results for k in res.kinds],
            sum(res.dry_km for res in results),
            sum(res.driven_cells for res in results),
            sum(res.cells_with_evidence for res in results),
            sum(res.cells_measured for res in results),
        )
    ]
    rows = [r for res in results for r in res.rows] + pooled
    pooled_with = [
        {"seed": "pooled", **r}
        for r in summarize_run(
            [r for res in results for r in res.station_patch_rows],
            [],
            [k for res in results for k in res.station_kinds],
            sum(res.dry_km for res in results),
            0,
            0,
        )
    ]
    station_rows = station_comparison([r for res in results for r in res.station_rows] + pooled_with, rows)
    pacsv.write_csv(pa.Table.from_pylist(station_rows), out / "stations.csv")
    columns = list(dict.fromkeys(k for r in rows for k in r))
    pacsv.write_csv(pa.Table.from_pylist([{k: r.get(k) for k in columns} for r in rows]), out / "metrics.csv")
    pacsv.write_csv(pa.Table.from_pylist(patch_rows), out / "patches.csv")
    pacsv.write_csv(pa.Table.from_pylist(cell_scores), out / "cells.csv")
    from roadgrip.evaluation.fleet_plots import plot_detection_delay, plot_map_vs_truth

    paths = {
        "metrics": out / "metrics.csv",
        "patches": out / "patches.csv",
        "cells": out / "cells.csv",
        "stations": out / "stations.csv",
        "report": out / "fleet.md",
        "log": out / "cloud.log",
        "map_vs_truth": plot_map_vs_truth(results[0], out / "map_vs_truth.png"),
        "detection_delay": plot_detection_delay(patch_rows, out / "detection_delay.png"),
    }
    for res in results:
        paths[f"estimates_seed{res.seed}"] = out / f"estimates_seed{res.seed}.parquet"
    report = (
        fleet_markdown(rows, patch_rows, results, config, wall_s, mode)
        + "\n"
        + stations_markdown(station_rows, results)
    )
    if sweep_rows is not None:
        from roadgrip.evaluation.fleet_plots import plot_tradeoff

        pacsv.write_csv(pa.Table.from_pylist(sweep_rows), out / "tradeoff.csv")
        chosen = choose(sweep_rows)
        paths["tradeoff"] = out / "tradeoff.csv"
        paths["tradeoff_plot"] = plot_tradeoff(sweep_rows, chosen, out / "tradeoff.png")
        report += "\n" + tradeoff_markdown(sweep_rows, chosen, sweep_s, tuning_seeds)
    (out / "fleet.md").write_text(report)
    return {"paths": paths, "rows": rows, "wall_s": wall_s, "sweep": sweep_rows}


STATION_GROUPS = ("mu<=0.2", "0.2-0.4", "0.4-0.6", "mu<=0.3", "all")
STATION_METRICS = (
    "recall",
    "recall_all",
    "within_3rd_pass",
    "time_to_first_median_s",
    "passes_to_first_median",
    "linger_max_s",
    "linger_over_10min",
    "cancelled_while_there",
    "warnings",
    "warnings_beside",
    "false_warnings",
)


def station_comparison(with_rows: list[dict], without_rows: list[dict]) -> list[dict]:
    """One row per seed (and pooled) and group: each of STATION_METRICS with the stations and without them."""
    bare = {(r["seed"], r["group"]): r for r in without_rows}
    out = []
    for r in with_rows:
        if r["group"] not in STATION_GROUPS:
            continue
        b = bare[(r["seed"], r["group"])]
        row = {"seed": r["seed"], "group": r["group"], "patches": r["patches"], "eligible": r["eligible"]}
        for name in STATION_METRICS:  # warnings are counted over the whole run ("all") only
            row[f"{name}_with"], row[f"{name}_without"] = r.get(name), b.get(name)
        out.append(row)
    return out


def stations_markdown(rows: list[dict], results: list[SeedResult]) -> str:
    lines = [
        "## Roadside stations: detection with and without them",
        "",
        (
            "Stations stand evenly along the network (chosen from the network alone); where one happens to stand on "
            "a patch is said beside it. The headline above is without them."
        ),
        "",
    ]
    for res in results:
        sites = ", ".join(
            f"{s.station_id} {'on ' + s.patch if s.patch else 'off the patches'}"
            + (f" (friction sensor, bias {s.friction_bias:+.2f})" if s.friction_sensor else "")
            for s in res.run.station_sites
        )
        lines.append(
            f"- seed {res.seed}: {res.run.station_reports} reports from {len(res.run.station_sites)} stations "
            f"({sites}); replaying the engine's input with the stations' rounds gives the service's warnings: "
            f"{'yes' if res.replay_matches_service else 'NO'}"
        )
    lines += [
        "",
        (
            "| seed | group | eligible | recall (with / without) | recall, all patches | by 3rd pass | "
            "time to 1st, median (min) | passes to 1st, median | longest linger (min) | cancelled while there | "
            "warnings | beside or after | false |"
        ),
        "| --- | --- | ---: | --- | --- | --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for r in rows:

        def pair(name, convert=_fmt, r=r):
            return f"{convert(r.get(f'{name}_with'))} / {convert(r.get(f'{name}_without'))}"

        lines.append(
            f"| {r['seed']} | {r['group']} | {r['eligible']} | {pair('recall')} | {pair('recall_all')} | "
            f"{pair('within_3rd_pass')} | {pair('time_to_first_median_s', _minutes)} | "
            f"{pair('passes_to_first_median')} | {pair('linger_max_s', _minutes)} | "
            f"{pair('cancelled_while_there')} | {pair('warnings')} | "
            f"{pair('warnings_beside')} | {pair('false_warnings')} |"
        )
    return "\n".join(lines) + "\n"


def _fmt(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "-"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def _minutes(value) -> str:
    return "-" if value is None else f"{value / 60:.1f}"


def fleet_markdown(
    rows: list[dict],
    patch_rows: list[dict],
    results: list[SeedResult],
    config: FleetConfig,
    wall_s: float,
    mode: str = "raw",
) -> str:
    seeds = ", ".join(str(r.seed) for r in results)
    timing = (
        f"Wall time {wall_s:.0f} s (simulation {sum(r.simulate_s for r in results):.0f} s, the service "
        f"{sum(r.run.wall_s for r in results):.0f} s); samples through the service "
        f"{sum(r.run.samples_sent for r in results):,}{' (estimated on board)' if mode == 'edge' else ''}, "
        f"rejected {sum(r.run.rejected for r in results)}."
    )
    title = (
        f"# Fleet benchmark: {config.vehicles} vehicles, {config.duration_s / 60:.0f} simulated minutes, report seeds "
        f"{seeds}; vehicles in {mode} mode"
        + (
            f"; {len(results[0].scenario.with_channels)} of them with the optional channels"
            if results[0].scenario.with_channels
            else ""
        )
    )
    lines = [
        title,
        "",
        timing,
        "",
        (
            "## Detection and warnings per band, the vehicles alone (recall and by-3rd-pass over patches driven by "
            ">= 3 vehicles while there; times in minutes; with the roadside stations: below)"
        ),
        "",
        (
            "| seed | group | patches | eligible | recall | recall (all) | by 1st / 2nd / 3rd pass | "
            "time to 1st (median / max) | "
            "passes to 1st (median / max) | warned and dried | lingering | linger (median / max) | > 10 min | "
            "censored | cancelled while there |"
        ),
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | --- | --- | ---: | ---: | --- | ---: | ---: | ---: |",
    ]
    for r in rows:
        if r["group"] == "dry":
            continue
        lines.append(
            f"| {r['seed']} | {r['group']} | {r['patches']} | {r['eligible']} | {_fmt(r['recall'])} | "
            f"{_fmt(r['recall_all'])} | {_fmt(r['within_1st_pass'])} / {_fmt(r['within_2nd_pass'])} / "
            f"{_fmt(r['within_3rd_pass'])} | {_minutes(r['time_to_first_median_s'])} / {_minutes(r['time_to_first_max_s'])} | "
            f"{_fmt(r['passes_to_first_median'], 1)} / {_fmt(r['passes_to_first_max'], 0)} | "
            f"{r['warned_and_dried']} | {r['lingering']} | {_minutes(r['linger_median_s'])} / "
            f"{_minutes(r['linger_max_s'])} | {r['linger_over_10min']} | {r['censored']} | "
            f"{r['cancelled_while_there']} |"
        )
    lines += [
        "",
        ("## Map (cells with evidence at every snapshot, against the true mu of their road) and false warnings"),
        "",
        (
            "Measured: cells with recent excited estimates or a station's report; bounded: cells where only calm "
            "passes proved a lower bound (the interval runs from about the bound to the grid's end, 1.5)."
        ),
        "",
        (
            "| seed | group | measured cells | MAE (range) | 90 % coverage (range) | MAE (lowest mu) | "
            "90 % coverage (lowest mu) | bounded cells | bounded: coverage (range) | bounded: coverage "
            "(lowest mu) |"
        ),
        "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        lines.append(
            f"| {r['seed']} | {r['group']} | {r['map_cells']} | {_fmt(r['map_mae'], 3)} | "
            f"{_fmt(r['map_coverage'])} | {_fmt(r['map_mae_low'], 3)} | {_fmt(r['map_coverage_low'])} | "
            f"{r['bounded_cells']} | {_fmt(r['bounded_coverage'])} | {_fmt(r['bounded_coverage_low'])} |"
        )
    lines += [
        "",
        (
            "| seed | warnings raised | on a patch | beside or after a patch | false | dry road km | "
            "false per 100 km | driven cells with map evidence (any / measured) | measured dry cells the map "
            "reads below 0.4 |"
        ),
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        if r["group"] == "all":
            lines.append(
                f"| {r['seed']} | {r['warnings']} | {r['warnings_on_patch']} | {r['warnings_beside']} | "
                f"{r['false_warnings']} | {r['dry_km']:.0f} | {_fmt(r['false_per_100km'], 3)} | "
                f"{_fmt(r['evidence_share'])} / {_fmt(r['measured_share'])} | "
                f"{_fmt(r['dry_cells_read_slippery'])} |"
            )
    lines += [
        "",
        "## Patches",
        "",
        (
            "| seed | patch | mu | there (min) | passes | observable passes | vehicles | detected | "
            "time to 1st (min) | passes to 1st | warnings | cancelled while there | passes in 10 min after drying | "
            "linger (min) | station | detected with stations |"
        ),
        "| --- | --- | ---: | --- | ---: | ---: | ---: | --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | --- |",
    ]
    for p in patch_rows:
        lines.append(
            f"| {p['seed']} | {p['patch']} | {p['mu']:.2f} | {p['appear_s'] / 60:.0f}-{p['dry_s'] / 60:.0f} | "
            f"{p['passes']} | {p['observable_passes']} | {p['vehicles']} | {_fmt(p['detected'])} | "
            f"{_minutes(p['time_to_first_s'])} | {_fmt(p['passes_to_first'])} | {p['warnings']} | "
            f"{p['cancelled_while_there']} | {p['passes_after_dry']} | "
            f"{_minutes(p['linger_s'])}{' (censored)' if p['censored'] else ''} | {p.get('station') or '-'} | "
            f"{_fmt(p.get('detected_with_stations'))} |"
        )
    return "\n".join(lines) + "\n"
