"""Why four low-mu patches of the fleet tuning seeds were warned passes after a pass that saturated a tire (the oracle's
"tire0.7 x3", results/trials/results/oracle_third_pass.py): per patch, its passes up to the first warning, and for
each pass with a tire at >= 0.7 of its mu F_z for >= 3 samples on the patch, what the vehicle's estimates said there
(the service run's own estimates; mu itself, which they lack, from probe_pass.py's offline replay) beside the
truth per sample (tire shares, slip, utilization, ABS/TCS/ESC), and the warning engine's verdict of each H3-cell pass.

    nice -n 19 python results/trials/estimators/trace_late_warnings.py --estimates /tmp/fleet_tuning

--estimates: the folder of a `roadgrip evaluate --benchmark fleet --seed 100 --seeds 3 --out DIR` run (its
estimates_seed<N>.parquet: every estimate the warning engine took). Tuning seeds only."""

import argparse
import pickle
import statistics
import sys
from pathlib import Path
from unittest import mock

import h3
import numpy as np
import pyarrow.parquet as pq

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "results"))
import oracle_third_pass as oracle

from roadgrip.cloud.domain.warnings import MIN_EXCITED_PER_PASS, THRESHOLD_MU
from roadgrip.data.schema import WHEELS
from roadgrip.evaluation.fleet_report import patch_truth

CASES = {  # seed -> (patch, first warned pass in the tuning run)
    102: [("mu<=0.2-00", 4), ("0.2-0.4-05", 11)],
    101: [("mu<=0.2-02", 11)],
    100: [("0.2-0.4-03", 4)],
}
SHARE = 0.7
LEAST = 3


def seed_data(seed: int, cache: Path):
    """The oracle's drives and tire shares, with the simulator's per-wheel columns in the drives' order (cached)."""
    path = cache / f"seed{seed}.pkl"
    if path.exists():
        return pickle.loads(path.read_bytes())
    tables = []
    real = oracle.simulate

    def keep(*args, **kwargs):
        tables.append(real(*args, **kwargs))
        return tables[-1]

    with mock.patch.object(oracle, "simulate", keep):
        scenario, drives, utilization, tire_share = oracle.drives_and_tires(seed)
    table = tables[-1]
    # the oracle's pairing (drives_and_tires): (vehicle, time) keys
    trips = {trip.scenario.run_id: trip for trip in scenario.trips}
    runs = table["run_id"].to_pylist()
    index = {v: k for k, v in enumerate(sorted(scenario.styles))}
    depart = np.array([trips[r].depart_s for r in runs])
    ticks = np.round(10.0 * (depart + table["t_s"].to_numpy())).astype(np.int64)
    truth_key = np.array([index[trips[r].vehicle_id] for r in runs], dtype=np.int64) * 10**8 + ticks
    drive_key = np.array([index[v] for v in drives.vehicle], dtype=np.int64) * 10**8 + np.round(
        10.0 * drives.t_s
    ).astype(np.int64)
    order = np.argsort(truth_key)
    at = order[np.searchsorted(truth_key[order], drive_key)]
    wheel = {}
    for w in WHEELS:
        for name in (f"fx_{w}_n", f"fy_{w}_n", f"fz_{w}_n", f"mu_{w}", f"slip_ratio_{w}", f"slip_angle_{w}_rad"):
            wheel[name] = table[name].to_numpy()[at]
    for name in ("ax_true_mps2", "ay_true_mps2"):
        wheel[name] = table[name].to_numpy()[at]
    data = (scenario, drives, utilization, tire_share, wheel)
    path.write_bytes(pickle.dumps(data))
    return data


def start_ms_of(estimates, drives) -> int:
    """The run's data clock start: the offset that puts the most estimate timestamps of one vehicle on its samples."""
    v = drives.vehicle[0]
    ts = estimates["timestamp_ms"].to_numpy()[estimates["vehicle_id"].to_numpy(zero_copy_only=False) == v]
    ms = np.round(drives.t_s[drives.vehicle == v] * 1000).astype(np.int64)
    guess = int(ts.min() - ms.min())
    best = max(range(guess - 5000, guess + 5001, 100), key=lambda s: np.isin(ts - s, ms).sum())
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--estimates", type=Path, required=True)
    parser.add_argument("--cache", type=Path, default=Path("/tmp/trace_cache"))
    parser.add_argument("--seeds", type=int, nargs="+", default=sorted(CASES))
    args = parser.parse_args()
    args.cache.mkdir(exist_ok=True)
    for seed in args.seeds:
        scenario, drives, utilization, tire_share, wheel = seed_data(seed, args.cache)
        estimates = pq.read_table(args.estimates / f"estimates_seed{seed}.parquet")
        start_ms = start_ms_of(estimates, drives)
        est_vehicle = estimates["vehicle_id"].to_numpy(zero_copy_only=False)
        est_ts = estimates["timestamp_ms"].to_numpy()
        truth = patch_truth(scenario, drives)
        patches = {p.name: p for p in truth.patches}
        abs_, tcs, esc = (
            drives.table[c].to_numpy(zero_copy_only=False) for c in ("abs_active", "tcs_active", "esc_active")
        )
        shares = np.array(
            [
                np.nan_to_num(
                    np.hypot(wheel[f"fx_{w}_n"], wheel[f"fy_{w}_n"]) / (wheel[f"mu_{w}"] * wheel[f"fz_{w}_n"])
                )
                for w in WHEELS
            ]
        )
        for name, warned in CASES[seed]:
            patch = patches[name]
            cells = truth.cells[name]
            print(
                f"\n## seed {seed}, patch {name} (mu {patch.mu:.3f}, appears {patch.appear_s:.0f} s), warned at pass {warned}"
            )
            print(f"patch cells: {sorted(cells)}")
            on_patch = patch.contains(drives.east_m, drives.north_m)
            for k, (vehicle, first, last) in enumerate(truth.passes[name][:warned], start=1):
                sel = np.flatnonzero(
                    on_patch & (drives.vehicle == vehicle) & (drives.t_s >= first) & (drives.t_s <= last)
                )
                n07 = int((tire_share[sel] >= SHARE).sum())
                print(
                    f"pass {k}: {vehicle} ({scenario.styles[vehicle]}, {scenario.kinds[vehicle].name}) {first:.1f}-{last:.1f} s,"
                    f" {sel.size} samples, speed {drives.table['speed_mps'].to_numpy()[sel].mean():.1f} m/s,"
                    f" bench-excited {int(drives.excited[sel].sum())}, tire>=0.7 {n07}, max share {tire_share[sel].max():.2f},"
                    f" max util {utilization[sel].max():.2f}, ABS {int(abs_[sel].sum())} TCS {int(tcs[sel].sum())} ESC {int(esc[sel].sum())}"
                )
                if n07 < LEAST:
                    continue
                # the service's estimates of this vehicle from 3 s before to 3 s after the pass
                lo, hi = start_ms + int((first - 3) * 1000), start_ms + int((last + 3) * 1000)
                mask = (est_vehicle == vehicle) & (est_ts >= lo) & (est_ts <= hi)
                rows = estimates.filter(mask).to_pylist()
                by_ts = {r["timestamp_ms"]: r for r in rows}
                window = np.flatnonzero(
                    (drives.vehicle == vehicle) & (drives.t_s >= first - 3) & (drives.t_s <= last + 3)
                )
                print(
                    "   t_s    on  cell   util  shares fl/fr/rl/rr     slip fl/fr/rl/rr (ratio)   ax    ay  A T E | est: excited lower upper proven"
                )
                for i in window.tolist():
                    ts = start_ms + round(drives.t_s[i] * 1000)
                    r = by_ts.get(ts)
                    cell = h3.latlng_to_cell(r["latitude_deg"], r["longitude_deg"], 10) if r else drives.cell[i]
                    est = (
                        f"{'X' if r['excited'] else '.'} {r['mu_lower']:.2f} {r['mu_upper']:.2f} {r['mu_proven'] or 0:.2f}"
                        if r
                        else "none"
                    )
                    print(
                        f"  {drives.t_s[i]:7.1f} {'P' if on_patch[i] else ' '} {cell[-6:]}{'*' if cell in cells else ' '}"
                        f" {utilization[i]:.2f}  "
                        + " ".join(f"{s:.2f}" for s in shares[:, i])
                        + "  "
                        + " ".join(f"{wheel[f'slip_ratio_{w}'][i]:+.3f}" for w in WHEELS)
                        + f"  {wheel['ax_true_mps2'][i]:+.2f} {wheel['ay_true_mps2'][i]:+.2f}"
                        f" {'A' if abs_[i] else '.'} {'T' if tcs[i] else '.'} {'E' if esc[i] else '.'} | {est}"
                    )
                # the engine's view: the vehicle's estimate passes per cell in the window
                by_cell = {}
                for r in sorted(rows, key=lambda r: r["timestamp_ms"]):
                    c = h3.latlng_to_cell(r["latitude_deg"], r["longitude_deg"], 10)
                    if not by_cell or list(by_cell)[-1] != c:
                        by_cell[c if c not in by_cell else f"{c}#{len(by_cell)}"] = []
                    by_cell[list(by_cell)[-1]].append(r)
                for c, rs in by_cell.items():
                    ex = [r for r in rs if r["excited"]]
                    med = statistics.median([r["mu_upper"] for r in ex]) if ex else float("nan")
                    verdict = "low" if len(ex) >= MIN_EXCITED_PER_PASS and med < THRESHOLD_MU else "-"
                    print(
                        f"  cell pass {c[:15]}{'*' if c[:15] in cells else ' '}: {len(rs)} estimates, {len(ex)} excited,"
                        f" median excited mu_upper {med:.2f}, min mu_upper {min(r['mu_upper'] for r in rs):.2f} -> {verdict}"
                    )


if __name__ == "__main__":
    main()
