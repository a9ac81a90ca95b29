"""An oracle's bound on the fleet benchmark's target "patches with mu <= 0.3: warned by the 3rd pass >= 0.9" (vehicles
alone; docs/RESULTS.md, "The fleet benchmark"): a warning needs a pass whose samples carry the patch's mu, so the
share of the target's patches with such a pass among their first three is what a perfect estimator and warning engine
could reach. From the truth alone: no estimator, no service.

    nice -n 19 python results/trials/results/oracle_third_pass.py [--seeds 0 1 2 100 101 102]

Per seed (default: the report seeds 0-2 and the tuning seeds 100-102 of `roadgrip evaluate --benchmark fleet`), the
benchmark's own scenario and drives (make_scenario, simulate_drives, FleetConfig's defaults), its passes while a patch
is there (fleet_report.patch_truth: find_passes) and whether a pass is observable (fleet_benchmark.observable) under
these definitions of an excited sample, each with the least count of them on the patch that a pass needs:
- bench: the benchmark's, true friction utilization (evaluation.bins.true_utilization) >= 0.5 or ABS, 3 samples;
- u0.5x1: the same samples, 1 is enough;
- u0.4x3: utilization >= 0.4 or ABS, 3 samples;
- tire x3, tire x1: a tire in the Dugoff model's saturated region, from the simulator's true forces: some wheel's
  |F| > mu F_z / 2 (below that a Dugoff tire's force is linear in slip, whatever mu: roadgrip/vehicle/tires/dugoff.py);
- tire0.7 x3: some wheel's |F| >= 0.7 mu F_z, 3 samples. A saturated Dugoff tire's force is mu F_z (1 - lambda / 2)
  against the linear line's mu F_z / (2 lambda), so at a share phi of mu F_z its slip is 1 / (4 phi (1 - phi)) of the
  linear line's: 1.04 at 0.6, 1.19 at 0.7, 1.56 at 0.8. Below about 0.7 a slip reading cannot tell saturation from a
  tire some 10-20 % softer than calibrated.
Prints one row per patch with mu <= TARGET_MU (its passes, distinct vehicles, the 1-based index in time order of its
first observable pass by each definition, '-' for none) and, per seed set, the bound: the share of the eligible
patches (driven by >= TARGET_MIN_VEHICLES vehicles, the target's denominator) whose first observable pass is among the
first TARGET_PASSES (and over all the patches in brackets). Takes about a minute a seed on 2 cores, 1.6 GB."""

import argparse
import dataclasses
import time
from unittest import mock

import numpy as np

from roadgrip.data.schema import WHEELS
from roadgrip.evaluation import fleet_benchmark
from roadgrip.evaluation.bins import true_utilization
from roadgrip.evaluation.fleet_benchmark import (
    EXCITED_UTILIZATION,
    OBSERVABLE_SAMPLES,
    make_scenario,
    observable,
    simulate_drives,
)
from roadgrip.evaluation.fleet_metrics import TARGET_MIN_VEHICLES, TARGET_MU, TARGET_PASSES
from roadgrip.evaluation.fleet_report import TUNING_SEEDS, patch_truth
from roadgrip.sim.simulate import simulate

REPORT_SEEDS = (0, 1, 2)
DEFINITIONS = ("bench", "u0.5x1", "u0.4x3", "tire x3", "tire x1", "tire0.7 x3")


def drives_and_tires(seed: int):
    """The benchmark's drives of the seed, and per sample of them the true utilization and the largest share of its
    wheel's mu F_z that a tire used: simulate_drives keeps only the wire format and a few truths, so the simulator's table it
    made them from (the true accelerations and per-wheel forces) is kept on the way and joined on (vehicle, time)."""
    scenario = make_scenario(seed)
    kept = []

    def keep(*args, **kwargs):
        kept.append(simulate(*args, **kwargs))
        return kept[-1]

    with mock.patch.object(fleet_benchmark, "simulate", keep):
        drives = simulate_drives(scenario, start_ms=0)
    table = kept.pop()
    with np.errstate(divide="ignore", invalid="ignore"):
        share = [
            np.hypot(table[f"fx_{w}_n"].to_numpy(), table[f"fy_{w}_n"].to_numpy())
            / (table[f"mu_{w}"].to_numpy() * table[f"fz_{w}_n"].to_numpy())
            for w in WHEELS
        ]
    tire_share = np.nan_to_num(np.max(share, axis=0))
    utilization = true_utilization(
        table["ax_true_mps2"].to_numpy(), table["ay_true_mps2"].to_numpy(), table["mu"].to_numpy()
    )
    trips = {trip.scenario.run_id: trip for trip in scenario.trips}
    runs = table["run_id"].to_pylist()
    index = {v: k for k, v in enumerate(sorted(scenario.styles))}

    def key(vehicles, t_s):
        """(vehicle, time in 0.1 s) as one integer: one sample each, since a vehicle's trips follow one another."""
        ticks = np.round(10.0 * np.asarray(t_s)).astype(np.int64)
        return np.array([index[v] for v in vehicles], dtype=np.int64) * 10**8 + ticks

    depart = np.array([trips[r].depart_s for r in runs])
    truth_key = key([trips[r].vehicle_id for r in runs], depart + table["t_s"].to_numpy())
    drive_key = key(drives.vehicle, drives.t_s)
    order = np.argsort(truth_key)
    at = np.searchsorted(truth_key[order], drive_key)
    paired = np.unique(truth_key).size == truth_key.size == drive_key.size
    if not (paired and np.array_equal(truth_key[order][at], drive_key)):
        raise RuntimeError("the simulator's table and the drives do not pair sample for sample")
    return scenario, drives, utilization[order][at], tire_share[order][at]


def first_observable(seed: int) -> list[dict]:
    """One row per patch with mu <= TARGET_MU: its passes, vehicles, and first observable pass by each definition."""
    scenario, drives, utilization, tire_share = drives_and_tires(seed)
    saturated = tire_share > 0.5
    abs_active = drives.table["abs_active"].to_numpy(zero_copy_only=False)
    if not np.array_equal((utilization >= EXCITED_UTILIZATION) | abs_active, drives.excited):
        raise RuntimeError("the utilization here is not the benchmark's (simulate_drives)")
    variants = {
        "bench": (drives, OBSERVABLE_SAMPLES),
        "u0.5x1": (drives, 1),
        "u0.4x3": (dataclasses.replace(drives, excited=(utilization >= 0.4) | abs_active), 3),
        "tire x3": (dataclasses.replace(drives, excited=saturated), 3),
        "tire x1": (dataclasses.replace(drives, excited=saturated), 1),
        "tire0.7 x3": (dataclasses.replace(drives, excited=tire_share >= 0.7), 3),
    }
    truth = patch_truth(scenario, drives)
    rows = []
    for patch in sorted(truth.patches, key=lambda p: p.name):
        if patch.mu > TARGET_MU:
            continue
        passes = truth.passes[patch.name]
        row = {"seed": seed, "patch": patch.name, "mu": patch.mu, "passes": len(passes)}
        row["vehicles"] = len({vehicle for vehicle, _, _ in passes})
        row["observable"] = truth.observable[patch.name]
        for name, (variant, least) in variants.items():
            hits = [k + 1 for k, p in enumerate(passes) if observable(variant, patch, [p], least)]
            row[name] = hits[0] if hits else None
        rows.append(row)
    return rows


def bound(rows: list[dict], name: str) -> str:
    """The share of the eligible patches observable by definition `name` within TARGET_PASSES, with its counts."""
    eligible = [r for r in rows if r["vehicles"] >= TARGET_MIN_VEHICLES]

    def within(group):
        return sum(r[name] is not None and r[name] <= TARGET_PASSES for r in group)

    return (
        f"{within(eligible) / len(eligible):.2f} ({within(eligible)}/{len(eligible)}; all {within(rows)}/{len(rows)})"
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[*REPORT_SEEDS, *TUNING_SEEDS])
    args = parser.parse_args()
    started = time.perf_counter()
    rows = [row for seed in args.seeds for row in first_observable(seed)]
    print(
        "| seed | patch | mu | passes | vehicles | observable passes (bench) | first observable pass: "
        + " | ".join(DEFINITIONS)
        + " |"
    )
    print("| ---: | --- | ---: | ---: | ---: | ---: | " + " | ".join("---:" for _ in DEFINITIONS) + " |")
    for r in rows:
        firsts = " | ".join("-" if r[name] is None else str(r[name]) for name in DEFINITIONS)
        print(
            f"| {r['seed']} | {r['patch']} | {r['mu']:.3f} | {r['passes']} | {r['vehicles']} | {r['observable']} | {firsts} |"
        )
    sets = {"report": REPORT_SEEDS, "tuning": TUNING_SEEDS, "all": tuple(args.seeds)}
    print(f"\nBound: eligible patches with an observable pass among their first {TARGET_PASSES}\n")
    print("| seeds | " + " | ".join(DEFINITIONS) + " |")
    print("| --- | " + " | ".join("---" for _ in DEFINITIONS) + " |")
    for label, seeds in sets.items():
        chosen = [r for r in rows if r["seed"] in seeds]
        if chosen:
            present = ",".join(str(s) for s in seeds if s in args.seeds)
            print(f"| {label} {present} | " + " | ".join(bound(chosen, n) for n in DEFINITIONS) + " |")
    print(f"\n{time.perf_counter() - started:.0f} s")


if __name__ == "__main__":
    main()
