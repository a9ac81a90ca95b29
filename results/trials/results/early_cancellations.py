"""Warnings on a patch that a dry pass cancelled while the patch was still there, from a fleet benchmark run's recorded
warning-engine input (DIR/estimates_seed{S}.parquet; the vehicles' estimates only, no station reports), replayed at
the product's settings. `--without-proven` replays the same rows with mu_proven taken out, to see which dry verdicts
came from what calm passes proved (docs/RESULTS.md, "Warnings cancelled too early").

    roadgrip evaluate --benchmark fleet --out runs/fleet
    python results/trials/results/early_cancellations.py runs/fleet [--without-proven]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, truth_by_cell
from roadgrip.evaluation.fleet_metrics import DRY_MU
from roadgrip.evaluation.fleet_sweep import replay, rounds_of


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the --out folder of a fleet benchmark run")
    parser.add_argument("--without-proven", action="store_true", help="replay with mu_proven taken out of the rows")
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
        for cell, detection_ms, _, reason, evidence_ms in replay(rounds_of(table)).values():
            for patch, cells in patches:
                raised_s, ended_s = (detection_ms - start_ms) / 1000.0, (evidence_ms - start_ms) / 1000.0
                if cell in cells and patch.appear_s <= raised_s <= patch.dry_s:
                    on_patch += 1
                    if reason == "recovered" and ended_s < patch.dry_s:
                        early += 1
                        print(
                            f"seed {seed}: patch mu {patch.mu:.2f}, warned at {raised_s / 60:.1f} min, cancelled at "
                            f"{ended_s / 60:.1f} min, the patch dried at {patch.dry_s / 60:.1f} min"
                        )
    print(f"{on_patch} warnings raised on a patch, {early} cancelled by a dry pass while it was still there")


if __name__ == "__main__":
    main()
