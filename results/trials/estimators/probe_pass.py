"""One vehicle's drive of a fleet tuning seed replayed through the guarded pmf as the service feeds it (a restart at
each gap over Settings.max_gap_s), printed sample by sample over a window: the estimate, and what the filter's state
says there (the inconsistency counter: evidence terms skipped because no cell explained them; the stiffness factor's
posterior mean; the slip line). For tracing a pass (trace_late_warnings.py) through the filter.

    nice -n 19 python results/trials/estimators/probe_pass.py SEED VEHICLE T0 T1

Reads the drives that trace_late_warnings.py cached (/tmp/trace_cache/seed<N>.pkl). Tuning seeds only."""

import argparse
import pickle
from pathlib import Path

import numpy as np

from roadgrip.estimators.learned import load_estimator

MAX_GAP_MS = 250


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seed", type=int)
    parser.add_argument("vehicle")
    parser.add_argument("t0", type=float)
    parser.add_argument("t1", type=float)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/trace_cache"))
    args = parser.parse_args()
    scenario, drives, utilization, tire_share, _ = pickle.loads((args.cache / f"seed{args.seed}.pkl").read_bytes())
    idx = np.flatnonzero((drives.vehicle == args.vehicle) & (drives.t_s <= args.t1))
    rows = drives.table.take(idx).to_pylist()
    t_s = drives.t_s[idx]
    estimator = load_estimator("pmf")
    state = estimator.start(scenario.kinds[args.vehicle])
    inner = estimator.inner
    last = None
    run = []
    for k, row in enumerate(rows):
        if last is not None and row["timestamp_ms"] - last > MAX_GAP_MS:
            if run:
                estimator.update_many(state, run)
            estimator.reset(state)
            run = []
        last = row["timestamp_ms"]
        if t_s[k] < args.t0:
            run.append(row)
            continue
        if run:
            estimator.update_many(state, run)
            run = []
        before = inner.calibration(state["inner"])["inconsistent"]
        est = estimator.update(state, row)
        cal = inner.calibration(state["inner"])
        i = idx[k]
        print(
            f"{t_s[k]:7.1f} share {tire_share[i]:.2f} util {utilization[i]:.2f} ax {row['accel_lon_mps2']:+.2f}"
            f" TCS {int(bool(row['tcs_active']))} ABS {int(bool(row['abs_active']))}"
            + (
                f" | mu {est.mu:.2f} [{est.mu_lower:.2f}, {est.mu_upper:.2f}] {'X' if est.excited else '.'}"
                if est
                else " | none"
            )
            + f" | skipped {cal['inconsistent'] - before} C {cal['stiffness_factor']:.2f}"
        )


if __name__ == "__main__":
    main()
