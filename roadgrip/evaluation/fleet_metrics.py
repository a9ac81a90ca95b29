"""Scores of the fleet benchmark (roadgrip/evaluation/fleet_benchmark.py has the definitions): per patch, per band and
over the run. Pure functions over plain records, so that hand-made cases test them.

Times are seconds on the run's clock (0 at its start).
"""

from __future__ import annotations

import math
import statistics
from dataclasses import dataclass

import h3

from roadgrip.cloud.domain.friction_map import BOUNDED, MEASURED
from roadgrip.cloud.domain.warnings import RECOVERED, THRESHOLD_MU
from roadgrip.fleet.network import Patch

BAND_LIMITS = (("mu<=0.2", 0.2), ("0.2-0.4", 0.4), ("0.4-0.6", 0.6))
DRY_MU = 0.6
TARGET_MU = 0.3
TARGET_MIN_VEHICLES = 3
TARGET_PASSES = 3
TARGET_LINGER_S = 600.0
SLIPPERY_MU = THRESHOLD_MU  # the service's default warning threshold (Settings.warning_threshold_mu)


def band_of(mu: float) -> str:
    """The band of a true mu: mu<=0.2, 0.2-0.4, 0.4-0.6, or "dry" (at or above DRY_MU)."""
    for name, high in BAND_LIMITS:
        if mu <= high and mu < DRY_MU:
            return name
    return "dry"


@dataclass(frozen=True)
class Warning:
    """A warning as the service stored it: its cell, when it was raised and when it ended (None: still active at the
    end of the run), and why it ended."""

    cell: str
    detection_s: float
    end_s: float | None
    reason: str | None = None


def warning_from_row(row: dict, start_ms: int) -> Warning:
    """A warning from the service's storage row (its latest event)."""
    event = row["message"]["event"]
    ended = row["status"] != "active"
    return Warning(
        row["cell"],
        (row["detection_ms"] - start_ms) / 1000.0,
        (event["evidence_ms"] - start_ms) / 1000.0 if ended else None,
        event["reason"] if ended else None,
    )


def classify(warning: Warning, patches: list[Patch], cells: dict[str, set[str]], validity_s: float) -> tuple:
    """("on", patch) when the warning's cell is a cell of a slippery patch (true mu below DRY_MU) that was there when it
    was raised; ("beside", patch) when its cell is a patch cell or one of their neighbours and it was raised while the
    patch was there or within validity_s after it dried; ("false", None) otherwise. Lowest mu first."""
    slippery = sorted((p for p in patches if p.mu < DRY_MU), key=lambda p: p.mu)
    for p in slippery:
        if warning.cell in cells[p.name] and p.appear_s <= warning.detection_s < p.dry_s:
            return "on", p
    for p in slippery:
        near = cells[p.name] | {n for c in cells[p.name] for n in h3.grid_disk(c, 1)}
        if warning.cell in near and p.appear_s <= warning.detection_s < p.dry_s + validity_s:
            return "beside", p
    return "false", None


def patch_outcome(
    patch: Patch,
    passes: list[tuple[str, float, float]],
    on: list[Warning],
    beside: list[Warning],
    run_end_s: float,
    passes_after_dry: int = 0,
    observable_passes: int | None = None,
) -> dict:
    """One patch's row. `passes`: (vehicle, entered, left) while it was there; `on` and `beside`: the warnings
    attributed to it (classify); `passes_after_dry`: passes over its place within TARGET_LINGER_S after it dried;
    `observable_passes`: the passes whose manoeuvre made mu observable (fleet_benchmark.observable).
    `cancelled_while_there`: its warnings on it that a dry pass cancelled ("recovered") before it dried, the patch
    unchanged: the warning engine read grip where the ice still was, or grip elsewhere as grip here.
    `last_low_s`: the last moment a vehicle drove on the patch's mu, at least its drying time: the simulator's mu is a
    function of the station, so a trip that planned to reach the patch before it dried drives it after (network.py),
    and its low reading then is true evidence of ice under its tires. The linger is counted from there: how long its
    warnings outlived the last ice the fleet drove on."""
    passes = sorted(passes, key=lambda p: p[1])
    vehicles = {p[0] for p in passes}
    warnings = [*on, *beside]
    first = min((w.detection_s for w in on), default=None)
    last_low_s = max([patch.dry_s, *(p[2] for p in passes)])
    row = {
        "patch": patch.name,
        "band": band_of(patch.mu),
        "mu": patch.mu,
        "appear_s": patch.appear_s,
        "dry_s": patch.dry_s,
        "passes": len(passes),
        "observable_passes": observable_passes,
        "vehicles": len(vehicles),
        "eligible": len(vehicles) >= TARGET_MIN_VEHICLES,
        "detected": first is not None,
        "time_to_first_s": None if first is None else first - patch.appear_s,
        "passes_to_first": None if first is None else sum(p[1] <= first for p in passes),
        "warnings": len(warnings),
        "cancelled_while_there": sum(w.reason == RECOVERED and w.end_s < patch.dry_s for w in on),
        "dried_in_run": patch.dry_s < run_end_s,
        "last_low_s": last_low_s,
        "passes_after_dry": passes_after_dry,
        "linger_s": None,
        "censored": False,
    }
    if warnings and last_low_s < run_end_s:
        ends = [run_end_s if w.end_s is None else w.end_s for w in warnings]
        row["linger_s"] = max(0.0, round(max(ends) - last_low_s, 3))  # to the clock's ms, not a float's last bit
        row["censored"] = any(w.end_s is None for w in warnings)
    return row


@dataclass(frozen=True)
class PatchTruth:
    """What scoring a seed's warnings needs of the truth, whatever the warnings: the patches, their cells, and per
    slippery patch its passes while there, the passes over its place within TARGET_LINGER_S after it dried, and its
    observable passes."""

    patches: tuple
    cells: dict  # patch name -> its cells
    passes: dict  # slippery patch name -> [(vehicle, entered s, left s)]
    passes_after_dry: dict  # slippery patch name -> count
    observable: dict  # slippery patch name -> count


def score_warnings(
    seed: int, truth: PatchTruth, warnings: list[Warning], validity_s: float, run_end_s: float
) -> tuple[list[str], list[dict]]:
    """The class of every warning ("on", "beside", "false"; `classify`) and one row per slippery patch
    (`patch_outcome`): the scoring shared by the run (fleet_report.py) and the sweep (fleet_sweep.py)."""
    patches = list(truth.patches)
    classes = [classify(w, patches, truth.cells, validity_s) for w in warnings]
    patch_rows = []
    for patch in patches:
        if patch.mu >= DRY_MU:
            continue
        on = [w for w, (kind, p) in zip(warnings, classes) if kind == "on" and p is patch]
        beside = [w for w, (kind, p) in zip(warnings, classes) if kind == "beside" and p is patch]
        patch_rows.append(
            {
                "seed": seed,
                **patch_outcome(
                    patch,
                    truth.passes[patch.name],
                    on,
                    beside,
                    run_end_s,
                    truth.passes_after_dry[patch.name],
                    truth.observable[patch.name],
                ),
            }
        )
    return [kind for kind, _ in classes], patch_rows


def score_cell(mu: float, mu_lower: float, mu_upper: float, truth: tuple[float, float]) -> dict:
    """The map's error in one cell against the range of true mu on the cell's road (0 inside it), whether its 90 %
    interval meets that range, and the cell's band (of its lowest true mu). Stricter, against the lowest true mu (the
    patch, in a cell that holds one): `error_low` and `covered_low` (the interval holds it)."""
    lo, hi = truth
    error = 0.0 if lo <= mu <= hi else min(abs(mu - lo), abs(mu - hi))
    return {
        "band": band_of(lo),
        "mu": mu,
        "mu_truth": lo,
        "error": error,
        "covered": mu_lower <= hi and mu_upper >= lo,
        "error_low": abs(mu - lo),
        "covered_low": mu_lower <= lo <= mu_upper,
    }


def _median(values) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


def _max(values) -> float | None:
    values = [v for v in values if v is not None]
    return max(values) if values else None


def _share(num: int, den: int) -> float | None:
    return num / den if den else None


def summarize(group: str, patch_rows: list[dict], cell_scores: list[dict]) -> dict:
    """Detection, delay, linger and map scores over the given patches and scored cells."""
    eligible = [r for r in patch_rows if r["eligible"]]
    detected = [r for r in patch_rows if r["detected"]]
    dried = [r for r in patch_rows if r["linger_s"] is not None]
    return {
        "group": group,
        "patches": len(patch_rows),
        "eligible": len(eligible),
        "recall": _share(sum(r["detected"] for r in eligible), len(eligible)),
        "recall_all": _share(len(detected), len(patch_rows)),
        **{
            f"within_{name}_pass": _share(
                sum(r["detected"] and r["passes_to_first"] <= passes for r in eligible), len(eligible)
            )
            for passes, name in ((1, "1st"), (2, "2nd"), (TARGET_PASSES, "3rd"))
        },
        "time_to_first_median_s": _median(r["time_to_first_s"] for r in detected),
        "time_to_first_max_s": _max(r["time_to_first_s"] for r in detected),
        "passes_to_first_median": _median(r["passes_to_first"] for r in detected),
        "passes_to_first_max": _max(r["passes_to_first"] for r in detected),
        "warned_and_dried": len(dried),
        "lingering": sum(r["linger_s"] > 0 for r in dried),
        "linger_median_s": _median(r["linger_s"] for r in dried),
        "linger_max_s": _max(r["linger_s"] for r in dried),
        "linger_over_10min": sum(r["linger_s"] > TARGET_LINGER_S for r in dried),
        "censored": sum(r["censored"] for r in dried),
        "cancelled_while_there": sum(r["cancelled_while_there"] for r in patch_rows),
        **_map_scores("map", [s for s in cell_scores if s["status"] == MEASURED]),
        **_map_scores("bounded", [s for s in cell_scores if s["status"] == BOUNDED]),
    }


def _map_scores(prefix: str, cell_scores: list[dict]) -> dict:
    """Error and coverage of the map's cells of one status (measured: excited evidence or a station; bounded: only
    what calm passes proved)."""
    n = len(cell_scores)
    return {
        f"{prefix}_cells": n,
        f"{prefix}_mae": None if not n else sum(s["error"] for s in cell_scores) / n,
        f"{prefix}_coverage": _share(sum(s["covered"] for s in cell_scores), n),
        f"{prefix}_mae_low": None if not n else sum(s["error_low"] for s in cell_scores) / n,
        f"{prefix}_coverage_low": _share(sum(s["covered_low"] for s in cell_scores), n),
    }


def summarize_run(
    patch_rows: list[dict],
    cell_scores: list[dict],
    kinds: list[str],
    dry_km: float,
    driven_cells: int,
    cells_with_evidence: int,
    cells_measured: int | None = None,
) -> list[dict]:
    """Rows per band, for the target's patches (mu <= TARGET_MU), for all slippery patches, and the whole run (false
    warnings per 100 km of dry road, the map over every scored cell, the share of driven cells with evidence of any
    kind and, where given, with a measurement). `kinds`: the class of every warning raised ("on", "beside",
    "false"). Cell scores carry the cell's map status ("measured" or "bounded")."""
    rows = []
    for band, _ in BAND_LIMITS:
        rows.append(
            summarize(band, [r for r in patch_rows if r["band"] == band], [s for s in cell_scores if s["band"] == band])
        )
    rows.append(
        summarize(
            f"mu<={TARGET_MU}",
            [r for r in patch_rows if r["mu"] <= TARGET_MU],
            [s for s in cell_scores if s["mu_truth"] <= TARGET_MU],
        )
    )
    rows.append(summarize("dry", [], [s for s in cell_scores if s["band"] == "dry"]))
    overall = summarize("all", [r for r in patch_rows if r["band"] != "dry"], cell_scores)
    false = kinds.count("false")
    dry_cells = [s for s in cell_scores if s["band"] == "dry" and s["status"] == MEASURED]
    overall.update(
        dry_cells_read_slippery=_share(sum(s["mu"] < SLIPPERY_MU for s in dry_cells), len(dry_cells)),
        warnings=len(kinds),
        warnings_on_patch=kinds.count("on"),
        warnings_beside=kinds.count("beside"),
        false_warnings=false,
        dry_km=dry_km,
        false_per_100km=false / (dry_km / 100.0) if dry_km > 0 else math.nan,
        evidence_share=_share(cells_with_evidence, driven_cells),
        measured_share=None if cells_measured is None else _share(cells_measured, driven_cells),
    )
    rows.append(overall)
    return rows
