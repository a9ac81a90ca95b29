"""What a fresh car's error at the limit owes to its unknown tire: pmf on the physics benchmark's validation split
with the catalogue profile (as the benchmark gives it), or with an oracle: the catalogue's profile with the run's true
tire stiffnesses (the drawn tire's, times the tire model's stiffness scale: what no fleet knows of a new car) and pmf's
stiffness prior narrowed around it (sd 0.1 in log instead of 0.6), by the physics benchmark's cells (mu band and true-utilization bin, ABS its own): samples, RMSE, skill against the
prior and 90 % coverage (docs/RESULTS.md, "What a fresh car can tell at the limit"). The oracle
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
from roadgrip.evaluation.baseline import prior_baseline
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.evaluation.physics_benchmark import cell_metrics, simulate_split


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


def main(channels: str, lead_in_s: float, variant: str) -> None:
    split = simulate_split("validation", channels=(channels,), lead_in_s=lead_in_s)
    runs, lead_ins = split.tables[channels]
    profiles = split.profiles
    if variant == "oracle":
        scenarios = {s.run_id: s for s, _ in split.drawn}
        profiles = {r: with_true_stiffness(p, scenarios[r]) for r, p in profiles.items()}
    e = estimates_on_runs(load_estimator("pmf"), runs, profiles, lead_ins=lead_ins)
    title = f"validation, [{channels}], lead-in {lead_in_s:.0f} s, {variant}"
    print(f"{title}: RMSE / skill against the prior / 90 % coverage")
    for row in cell_metrics(e, prior_baseline().mu_median):
        if row["n"]:
            print(
                f"  mu {row['band']:>7} u {row['bin']:>7}: {row['n']:6d} samples  {row['rmse']:.3f} / "
                f"{row['skill']:+.2f} / {row['coverage']:.2f}"
            )
    by_group(e, split, title)


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), sys.argv[3])
