"""The vehicles-alone warning scores of a fleet benchmark run, rescored with the warning engine of the code on
PYTHONPATH: the run's recorded warning-engine input (DIR/estimates_seed{S}.parquet) replayed at the product's settings
(what fleet_report.run_seed does for its headline), against the truth of the same seeds simulated again. Run it with
PYTHONPATH at another checkout to score an older engine on the same input: a before/after of a rule of the warning
engine with the estimator held fixed (docs/RESULTS.md, "Warnings that last: the last two misses").

    roadgrip evaluate --benchmark fleet --seed 100 --seeds 3 --out runs/tune
    PYTHONPATH=. python results/trials/results/warnings_rescore.py runs/tune
    PYTHONPATH=/path/to/older/checkout python results/trials/results/warnings_rescore.py runs/tune
"""

from __future__ import annotations

import argparse
from pathlib import Path

import pyarrow.parquet as pq

from roadgrip.cloud.settings import Settings
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, simulate_drives
from roadgrip.evaluation.fleet_metrics import TARGET_MU, score_warnings, summarize_run
from roadgrip.evaluation.fleet_report import patch_truth
from roadgrip.evaluation.fleet_sweep import as_warnings, replay, rounds_of


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the --out folder of a fleet benchmark run")
    args = parser.parse_args()
    paths = sorted(args.run.glob("estimates_seed*.parquet"))
    if not paths:
        raise SystemExit(f"no estimates_seed*.parquet in {args.run}: run roadgrip evaluate --benchmark fleet first")
    config = FleetConfig()
    validity_s = Settings.model_fields["warning_validity_s"].default
    all_rows, all_kinds = [], []
    for path in paths:
        seed = int(path.stem.removeprefix("estimates_seed"))
        table = pq.read_table(path)
        scenario = make_scenario(seed, config)
        drives = simulate_drives(scenario, 0)  # the truth is in seconds from the run's start; on the data clock from 0
        # the run's start: its first estimate is that of its first sample (each sample is estimated)
        start_ms = int(table["timestamp_ms"].to_numpy().min()) - int(drives.table["timestamp_ms"].to_numpy().min())
        truth = patch_truth(scenario, drives)
        warnings = as_warnings(replay(rounds_of(table)), start_ms)
        kinds, patch_rows = score_warnings(seed, truth, warnings, validity_s, config.duration_s)
        print(f"seed {seed}: the run started at {start_ms} ms")
        all_rows += patch_rows
        all_kinds += kinds
        for r in patch_rows:
            if r["linger_s"] is not None or r["cancelled_while_there"]:
                print(
                    f"seed {seed} {r['patch']} mu {r['mu']:.2f}: linger {r['linger_s']} s, cancelled while there "
                    f"{r['cancelled_while_there']}"
                )
    rows = {r["group"]: r for r in summarize_run(all_rows, [], all_kinds, 0.0, 0, 0)}
    target, overall = rows[f"mu<={TARGET_MU}"], rows["all"]
    print(
        f"pooled, mu <= {TARGET_MU}: recall {target['recall']:.2f}, by the 3rd pass {target['within_3rd_pass']:.2f}, "
        f"linger median / max {target['linger_median_s']:.1f} / {target['linger_max_s']:.1f} s; all bands: "
        f"{overall['linger_over_10min']} lingering > 10 min, {overall['cancelled_while_there']} cancelled while the "
        f"patch was there; warnings {overall['warnings']} ({overall['warnings_on_patch']} on a patch, "
        f"{overall['warnings_beside']} beside or after), {overall['false_warnings']} false"
    )


if __name__ == "__main__":
    main()
