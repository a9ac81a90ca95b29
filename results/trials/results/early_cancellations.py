"""Warnings on a patch that a dry pass cancelled while the patch was still there, from a fleet benchmark run's recorded
warning-engine input (DIR/estimates_seed{S}.parquet; the vehicles' estimates only, no station reports), replayed at
the product's settings. `--without-proven` replays the same rows with mu_proven taken out, to see which dry verdicts
came from what calm passes proved (docs/RESULTS.md, "Warnings cancelled too early"). `--trace` prints, for each such
cancellation, the dry pass that cancelled it: its vehicle and time, where its estimates proved grip (distance from the
patch's centre against its radius, metres) and where the warning's low evidence lay (its spots, the same way), so that
one can see whether the pass drove over the low place or beside it (docs/RESULTS.md, "Warnings that last").

    roadgrip evaluate --benchmark fleet --seed 100 --seeds 3 --out runs/tune     # the tuning seeds
    python results/trials/results/early_cancellations.py runs/tune [--without-proven] [--trace]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import h3
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pymap3d

from roadgrip.cloud.domain import warnings as engine_module
from roadgrip.cloud.domain.warnings import DRY, RECOVERED
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, truth_by_cell
from roadgrip.evaluation.fleet_metrics import DRY_MU
from roadgrip.evaluation.fleet_sweep import replay, rounds_of


def _distances_m(network, patch, positions) -> list[float]:
    """Distances (m) of (lat, lon) positions from the patch's centre."""
    if not positions:
        return []
    lat, lon = np.array(positions).T
    east, north, _ = pymap3d.geodetic2enu(lat, lon, np.zeros(lat.size), *network.origin, 0.0)
    return np.hypot(east - patch.east_m, north - patch.north_m).round(0).tolist()


class _Tracer:
    """Wraps WarningEngine._apply: for every dry pass applied to a cell with a warning, what it was and what the cell's
    place held before it."""

    def __init__(self):
        self.cancels: dict[str, tuple] = {}  # warning_id -> (the pass, the place's spots) of the cancelling pass
        self._original = engine_module.WarningEngine._apply

    def __enter__(self):
        tracer, original = self, self._original

        def apply(engine, finished, verdict, t, now_ms, events, *, station=False):
            near = h3.grid_disk(finished.cell, 1)  # a dry pass may clear the places of neighbours waiting on its cell
            spots = {c: engine.cell_states_[c].place.keys() for c in near if c in engine.cell_states_}
            before = len(events)
            original(engine, finished, verdict, t, now_ms, events, station=station)
            if verdict == DRY:
                for event in events[before:]:
                    if event.reason == RECOVERED:
                        tracer.cancels[event.warning_id] = (finished, spots.get(event.cell, ()))

        engine_module.WarningEngine._apply = apply
        return self

    def __exit__(self, *exc):
        engine_module.WarningEngine._apply = self._original


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the --out folder of a fleet benchmark run")
    parser.add_argument("--without-proven", action="store_true", help="replay with mu_proven taken out of the rows")
    parser.add_argument("--trace", action="store_true", help="print where each early cancelling pass proved grip")
    args = parser.parse_args()
    paths = sorted(args.run.glob("estimates_seed*.parquet"))
    if not paths:
        raise SystemExit(f"no estimates_seed*.parquet in {args.run}: run roadgrip evaluate --benchmark fleet first")
    on_patch = early = 0
    for path in paths:
        seed = int(path.stem.removeprefix("estimates_seed"))
        scenario = make_scenario(seed, FleetConfig())
        table = pq.read_table(path)
        if args.without_proven:
            table = table.set_column(
                table.schema.get_field_index("mu_proven"), "mu_proven", pa.nulls(table.num_rows, pa.float64())
            )
        start_ms = int(table["timestamp_ms"].to_numpy().min()) // 1000 * 1000
        patches = []
        for patch in scenario.network.patches:
            if patch.mu < DRY_MU:
                truth = truth_by_cell(scenario.network, (patch.appear_s + patch.dry_s) / 2)
                patches.append((patch, {c for c, (lowest, _) in truth.items() if abs(lowest - patch.mu) < 1e-9}))
        with _Tracer() as tracer:
            latest = replay(rounds_of(table))
        for warning_id, (cell, detection_ms, _, reason, evidence_ms) in latest.items():
            for patch, cells in patches:
                raised_s, ended_s = (detection_ms - start_ms) / 1000.0, (evidence_ms - start_ms) / 1000.0
                if cell in cells and patch.appear_s <= raised_s <= patch.dry_s:
                    on_patch += 1
                    if reason == "recovered" and ended_s < patch.dry_s:
                        early += 1
                        print(
                            f"seed {seed}: patch {patch.name} mu {patch.mu:.2f} radius {patch.radius_m:.0f} m, warned "
                            f"at {raised_s / 60:.1f} min, cancelled at {ended_s / 60:.1f} min, the patch dried at "
                            f"{patch.dry_s / 60:.1f} min"
                        )
                        if args.trace and warning_id in tracer.cancels:
                            finished, spots = tracer.cancels[warning_id]
                            spot_at = [h3.cell_to_latlng(s) for s in spots if s and h3.is_valid_cell(s)]
                            print(
                                f"  cancelled by {finished.vehicle_id} in "
                                f"{(finished.first_ms - start_ms) / 1000:.0f}-{(finished.last_ms - start_ms) / 1000:.0f}"
                                f" s: {len(finished.uppers)} excited, proven max {finished.proven:.2f}, median "
                                f"mu_lower {np.median(finished.lowers) if finished.lowers else float('nan'):.2f}\n"
                                f"  grip proven at (m from centre) {_distances_m(scenario.network, patch, finished.grip_at)}"
                                f"\n  low read in the pass at {_distances_m(scenario.network, patch, finished.low_at)}"
                                f"\n  the place's spots at {_distances_m(scenario.network, patch, spot_at)}"
                            )
    print(f"{on_patch} warnings raised on a patch, {early} cancelled by a dry pass while it was still there")


if __name__ == "__main__":
    main()
