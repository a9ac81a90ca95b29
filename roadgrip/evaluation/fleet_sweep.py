"""The warning engine's trade-off curve (issue 16, item 5): the estimate rows the service's warning engine took in a
fleet benchmark run (fleet_benchmark.EngineRecorder: per round, its clock and its rows) are replayed offline into
engines with other settings, each built as the service builds its own (roadgrip/cloud/pipeline/fanout.py
new_warning_engine, the swept values as overrides), and each setting is scored by the benchmark's own scoring
(fleet_metrics.score_warnings and summarize_run). Replaying at the service's settings gives the service's
warnings exactly (checked on every run: `replay_matches_service`), since the engine is a pure function of its calls;
the roadside stations' evidence (EngineRecorder.station_table) is replayed in its rounds too
(`WarningEngine.station_evidence`). The sweep is run on the tuning seeds (fleet_report.TUNING_SEEDS), never on the
seeds the benchmark reports.

The product's setting is chosen from the curve by RULE (`choose`).
"""

from __future__ import annotations

import itertools
import multiprocessing
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor

import numpy as np
import pyarrow as pa

from roadgrip.cloud.domain.warnings import CANCELLED
from roadgrip.cloud.pipeline.fanout import new_warning_engine
from roadgrip.cloud.settings import Settings
from roadgrip.evaluation.fleet_metrics import TARGET_MU, Warning, score_warnings, summarize_run

# the engine's parameters swept, each with its Settings field; the others stay at the product's value
PARAMETERS = {
    "threshold_mu": "warning_threshold_mu",
    "min_low_passes": "warning_min_low_passes",
    "min_excited_per_pass": "warning_min_excited_per_pass",
    "validity_s": "warning_validity_s",
}
GRID = {
    "threshold_mu": (0.3, 0.4, 0.5),
    "min_low_passes": (1, 2, 3),
    "min_excited_per_pass": (2, 3, 5),
    "validity_s": (300.0, 600.0),
}  # 54 settings: a replay of a seed takes about 2 s
RULE = (
    "of the settings with no false warning on any seed, the highest recall of the mu <= 0.3 patches; ties: the "
    "most of them warned by the 3rd pass, then fewer passes to the first warning (median), then the shorter "
    "longest linger after drying, then the fewest parameters changed from the product's"
)


def product_setting(settings: Settings | None = None) -> dict:
    """The swept parameters at the product's values (Settings defaults, or `settings`)."""
    settings = settings or Settings()
    return {name: getattr(settings, field) for name, field in PARAMETERS.items()}


def grid_settings(grid: dict = GRID) -> list[dict]:
    unknown = set(grid) - set(PARAMETERS)
    if unknown:
        raise ValueError(f"grid: unknown parameters {sorted(unknown)}; known: {sorted(PARAMETERS)}")
    names = list(grid)
    return [dict(zip(names, values)) for values in itertools.product(*(grid[n] for n in names))]


def _numbered_rounds(table: pa.Table) -> list[tuple[int, int, list[dict]]]:
    rows = table.drop_columns(["round", "now_ms"]).to_pylist()
    rounds = table["round"].to_numpy()
    now = table["now_ms"].to_numpy()
    starts = np.concatenate([[0], np.flatnonzero(np.diff(rounds)) + 1]) if rounds.size else np.array([], int)
    ends = np.concatenate([starts[1:], [rounds.size]]) if rounds.size else np.array([], int)
    return [(int(rounds[a]), int(now[a]), rows[a:b]) for a, b in zip(starts.tolist(), ends.tolist())]


def rounds_of(estimates: pa.Table, stations: pa.Table | None = None) -> list[tuple[int, list[dict]]]:
    """(now_ms, rows) per recorded round, in order: the estimates' rounds and, when given, the stations' (whose rows
    hold a "cell")."""
    numbered = _numbered_rounds(estimates) + ([] if stations is None else _numbered_rounds(stations))
    return [(now_ms, rows) for _, now_ms, rows in sorted(numbered, key=lambda r: r[0])]


def replay(rounds: list[tuple[int, list[dict]]], settings: Settings | None = None, **overrides) -> dict[str, tuple]:
    """Feed the rounds to a fresh warning engine of `settings` (the product's by default) with `overrides` (WarningEngine
    arguments); every warning's latest event, by warning_id (what the service stores): warning_id -> (cell,
    detection_ms, status, reason, evidence_ms)."""
    engine = new_warning_engine(settings or Settings(), **overrides)
    latest: dict[str, tuple] = {}
    for now_ms, rows in rounds:
        events = engine.station_evidence(rows, now_ms) if "cell" in rows[0] else engine.update(rows, now_ms)
        for e in events:
            latest[e.warning_id] = (e.cell, e.detection_ms, e.status, e.reason, e.evidence_ms)
    return latest


def as_warnings(latest: dict[str, tuple], start_ms: int) -> list[Warning]:
    """The replayed warnings as fleet_metrics.Warning (times from the run's start), as fleet_metrics.warning_from_row
    makes them from the service's storage."""
    out = []
    for cell, detection_ms, status, reason, evidence_ms in latest.values():
        ended = status == CANCELLED
        out.append(
            Warning(
                cell,
                (detection_ms - start_ms) / 1000.0,
                (evidence_ms - start_ms) / 1000.0 if ended else None,
                reason if ended else None,
            )
        )
    return sorted(out, key=lambda w: (w.detection_s, w.cell))


def _same(a: list[Warning], b: list[Warning]) -> bool:
    return sorted(a, key=lambda w: (w.detection_s, w.cell)) == sorted(b, key=lambda w: (w.detection_s, w.cell))


_REPLAYS = None  # (settings, [(rounds, start_ms)] per seed) while a sweep runs


def _replay_seeds(overrides: dict) -> list[list[Warning]]:
    settings, seeds = _REPLAYS
    return [as_warnings(replay(rounds, settings, **overrides), start_ms) for rounds, start_ms in seeds]


def sweep(
    results: list,
    run_end_s: float,
    grid: dict = GRID,
    settings: Settings | None = None,
    progress: Callable[[str, float], None] | None = None,
    workers: int = 2,
) -> list[dict]:
    """One row per setting of the grid (and the product's setting, flagged `product`): the pooled scores of the
    target's patches (mu <= 0.3) and of the run over the seeds of `results` (fleet_report.SeedResult), and the false
    warnings per seed. The product's setting is replayed too and compared with the service's own warnings."""
    settings = settings or Settings()
    product = product_setting(settings)
    candidates = [{**product, **setting} for setting in grid_settings(grid)]  # unswept: the product's value
    if product not in candidates:
        candidates.append(product)
    say = progress or (lambda message, fraction: None)
    global _REPLAYS
    _REPLAYS = (
        settings,
        [(rounds_of(res.run.estimates, res.run.stations), res.start_ms) for res in results],
    )  # the workers inherit them (fork)
    try:
        if workers > 1:
            with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
                replayed = []
                for j, out in enumerate(pool.map(_replay_seeds, candidates)):
                    replayed.append(out)
                    say(f"sweep: setting {j + 1} of {len(candidates)}", (j + 1) / len(candidates))
        else:
            replayed = [_replay_seeds(setting) for setting in candidates]
    finally:
        _REPLAYS = None
    per_setting: list[list[tuple]] = [[] for _ in candidates]  # (seed result, kinds, patch rows)
    matches = True
    for j, setting in enumerate(candidates):
        for res, warnings in zip(results, replayed[j]):
            if setting == product:
                matches = matches and _same(warnings, res.service_warnings)
            kinds, patch_rows = score_warnings(res.seed, res.truth, warnings, setting["validity_s"], run_end_s)
            per_setting[j].append((res, kinds, patch_rows))
    rows = []
    for setting, seeds in zip(candidates, per_setting):
        runs = summarize_run(
            [r for _, _, rows_ in seeds for r in rows_],
            [],
            [k for _, kinds, _ in seeds for k in kinds],
            sum(res.dry_km for res, _, _ in seeds),
            0,
            0,
        )
        target = next(r for r in runs if r["group"] == f"mu<={TARGET_MU}")
        overall = next(r for r in runs if r["group"] == "all")
        row = {
            **setting,
            "product": setting == product,
            "patches": target["eligible"],
            "recall": target["recall"],
            "within_3rd_pass": target["within_3rd_pass"],
            "passes_to_first_median": target["passes_to_first_median"],
            "passes_to_first_max": target["passes_to_first_max"],
            "time_to_first_median_s": target["time_to_first_median_s"],
            "linger_median_s": target["linger_median_s"],
            "linger_max_s": target["linger_max_s"],
            "linger_over_10min": target["linger_over_10min"],
            "cancelled_while_there": overall["cancelled_while_there"],
            "recall_all_slippery": overall["recall"],
            "warnings": overall["warnings"],
            "warnings_on_patch": overall["warnings_on_patch"],
            "warnings_beside": overall["warnings_beside"],
            "false_warnings": overall["false_warnings"],
            "false_per_100km": overall["false_per_100km"],
            "dry_km": overall["dry_km"],
            "max_false_per_seed": max(kinds.count("false") for _, kinds, _ in seeds),
            "false_per_seed": " ".join(str(kinds.count("false")) for _, kinds, _ in seeds),
            "seeds": " ".join(str(res.seed) for res, _, _ in seeds),
        }
        if setting == product:
            row["replay_matches_service"] = matches
        rows.append(row)
    return rows


def _key(row: dict, product: dict | None = None) -> tuple:
    def neg(v):
        return -(v if v is not None else -1.0)

    def pos(v):
        return v if v is not None else float("inf")

    return (
        neg(row["recall"]),
        neg(row["within_3rd_pass"]),
        pos(row["passes_to_first_median"]),
        pos(row["linger_max_s"]),
        sum(row.get(n) != product.get(n) for n in PARAMETERS) if product else 0,
        not row["product"],
    )


def choose(rows: Iterable[dict]) -> dict | None:
    """The setting RULE picks, or None when every setting raised a false warning on some seed."""
    rows = list(rows)
    product = next((r for r in rows if r["product"]), None)
    safe = [r for r in rows if r["max_false_per_seed"] == 0]
    return min(safe, key=lambda r: _key(r, product)) if safe else None


def _fmt(value, digits: int = 2) -> str:
    if value is None or (isinstance(value, float) and np.isnan(value)):
        return "-"
    return f"{value:.{digits}f}" if isinstance(value, float) else str(value)


def tradeoff_markdown(rows: list[dict], chosen: dict | None, sweep_s: float, seeds: Iterable[int] = ()) -> str:
    """The curve as a table (settings with no false warning on any seed first, each group by the rule's order);
    `seeds`: the tuning seeds it was replayed on."""
    product = next((r for r in rows if r["product"]), None)
    safe = sorted((r for r in rows if r["max_false_per_seed"] == 0), key=lambda r: _key(r, product))
    unsafe = sorted((r for r in rows if r["max_false_per_seed"] > 0), key=lambda r: _key(r, product))
    lines = [
        (
            f"## The warning engine's trade-off (replayed estimates of the tuning seeds "
            f"{', '.join(str(s) for s in seeds) or '-'}, not the report's; {len(rows)} settings, {sweep_s:.0f} s)"
        ),
        "",
        f"Rule: {RULE}. Chosen: "
        + (
            "none (every setting raised a false warning)"
            if chosen is None
            else ", ".join(f"{k} {chosen[k]}" for k in PARAMETERS)
        )
        + ".",
        "",
        (
            "| threshold_mu | min_low_passes | min_excited_per_pass | validity_s | product | recall (mu <= 0.3) | "
            "by 3rd pass | passes to 1st (median / max) | linger (median / max, min) | > 10 min | warnings | "
            "beside or after a patch | false (per seed) | false per 100 km | cancelled while there |"
        ),
        "| ---: | ---: | ---: | ---: | --- | ---: | ---: | --- | --- | ---: | ---: | ---: | --- | ---: | ---: |",
    ]
    for r in safe + unsafe:
        linger = [None if v is None else v / 60 for v in (r["linger_median_s"], r["linger_max_s"])]
        lines.append(
            f"| {r['threshold_mu']} | {r['min_low_passes']} | {r['min_excited_per_pass']} | "
            f"{r['validity_s']:.0f} | {'yes' if r['product'] else ''} | {_fmt(r['recall'])} | "
            f"{_fmt(r['within_3rd_pass'])} | {_fmt(r['passes_to_first_median'], 1)} / "
            f"{_fmt(r['passes_to_first_max'], 0)} | {_fmt(linger[0], 1)} / {_fmt(linger[1], 1)} | "
            f"{r['linger_over_10min']} | {r['warnings']} | {r['warnings_beside']} | {r['false_per_seed']} | "
            f"{_fmt(r['false_per_100km'], 3)} | {r['cancelled_while_there']} |"
        )
    if product is not None:
        lines += [
            "",
            (
                f"Replaying the product's setting reproduces the service's warnings: "
                f"{'yes' if product.get('replay_matches_service') else 'NO'}."
            ),
        ]
    return "\n".join(lines) + "\n"
