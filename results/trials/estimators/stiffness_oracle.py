"""What a fresh car's error at the limit owes to its unknown tire: pmf on the physics benchmark's validation split
with the catalogue profile (as the benchmark gives it), or with an oracle: the catalogue's profile with the run's true
tire stiffnesses (the drawn tire's, times the tire model's stiffness scale: what no fleet knows of a new car) and pmf's
stiffness prior narrowed around it (sd 0.1 in log instead of 0.6), by mu band and true-utilization bin (ABS samples
their own bin): samples, RMSE and 90 % coverage (docs/RESULTS.md, "What a fresh car can tell at the limit"). The oracle
patches pmf's prior before numba compiles it, into a cache of its own: run each variant in its own process.

    python results/trials/estimators/stiffness_oracle.py base 0 catalogue   # a fresh car, as the benchmark
    python results/trials/estimators/stiffness_oracle.py base 0 oracle      # ... knowing its tires' stiffness
"""

import atexit
import dataclasses
import os
import shutil
import sys
import tempfile

import numpy as np

if sys.argv[3] == "oracle":  # before numba reads pmf's globals, and never into the package's own cache
    os.environ["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(prefix="roadgrip-oracle-")
    atexit.register(shutil.rmtree, os.environ["NUMBA_CACHE_DIR"], ignore_errors=True)
    from roadgrip.estimators import pmf

    narrow = np.exp(-0.5 * (np.log(pmf.C_FACTORS) / 0.1) ** 2)
    pmf.C_PRIOR[:] = narrow / narrow.sum()

from ice_at_the_limit import by_group  # this folder's: run as a script

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs, true_utilization
from roadgrip.evaluation.physics_benchmark import simulate_split


def with_true_stiffness(profile, scenario):
    """The profile with each axle's tire stiffnesses the run's own (its drawn tire's, times the model's scale)."""
    scale = scenario.tire.stiffness_scale

    def tire(catalogue, drawn):
        return dataclasses.replace(
            catalogue,
            longitudinal_stiffness_per_load=drawn.longitudinal_stiffness_per_load * scale,
            cornering_stiffness_per_load_per_rad=drawn.cornering_stiffness_per_load_per_rad * scale,
        )

    vehicle = scenario.vehicle
    return profile.replace(
        tire_front=tire(profile.tire_front, vehicle.tire_front), tire_rear=tire(profile.tire_rear, vehicle.tire_rear)
    )


def table(e) -> dict:
    u = true_utilization(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"])
    abs_on = e["abs_active"].astype(bool)
    bins = {"< 0.5": (u < 0.5) & ~abs_on, "0.5-0.8": (u >= 0.5) & (u < 0.8) & ~abs_on, ">= 0.8": (u >= 0.8) & ~abs_on}
    bins["ABS"] = abs_on
    bands = {"<= 0.3": e["mu"] <= 0.3, "0.3-0.6": (e["mu"] > 0.3) & (e["mu"] < 0.6), ">= 0.6": e["mu"] >= 0.6}
    bands["all"] = np.ones_like(abs_on)
    out = {}
    for band, b in bands.items():
        for name, k in bins.items():
            k = k & b
            err = e["mu_est"][k] - e["mu"][k]
            cover = (e["mu_lower"][k] <= e["mu"][k]) & (e["mu"][k] <= e["mu_upper"][k])
            out[(band, name)] = (int(k.sum()), float(np.sqrt((err**2).mean())), float(cover.mean()))
    return out


def main(channels: str, lead_in_s: float, variant: str) -> None:
    split = simulate_split("validation", channels=(channels,), lead_in_s=lead_in_s)
    runs, lead_ins = split.tables[channels]
    profiles = split.profiles
    if variant == "oracle":
        scenarios = {s.run_id: s for s, _ in split.drawn}
        profiles = {r: with_true_stiffness(p, scenarios[r]) for r, p in profiles.items()}
    e = estimates_on_runs(load_estimator("pmf"), runs, profiles, lead_ins=lead_ins)
    title = f"validation, [{channels}], lead-in {lead_in_s:.0f} s, {variant}"
    print(f"{title}: RMSE / 90 % coverage")
    for (band, name), (n, rmse, cover) in table(e).items():
        print(f"  mu {band:>7} u {name:>7}: {n:6d} samples  {rmse:.3f} / {cover:.2f}")
    by_group(e, split, title)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3])
