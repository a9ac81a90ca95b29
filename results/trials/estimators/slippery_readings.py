"""Samples of roads of 0.4 and more that pmf reads with mu_upper below 0.4 (a false slippery reading), by manoeuvre, on
a physics benchmark split, for a car seen for the first time or after a calm lead-in (docs/RESULTS.md, "This
release: the test split's one look").

    python results/trials/estimators/slippery_readings.py validation 0      # a fresh car, the base channels
    python results/trials/estimators/slippery_readings.py test 180          # after 180 s of calm driving (once)
"""

import collections
import sys

import numpy as np
import pyarrow.compute as pc

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import catalogue_profile, estimates_on_runs
from roadgrip.sim.presets import LEAD_IN_SUFFIX, physics_benchmark_runs, physics_lead_in
from roadgrip.sim.simulate import simulate


def main(split: str, lead_in_s: float) -> None:
    drawn = physics_benchmark_runs(split)
    scenarios = [s for s, _ in drawn]
    leads = [physics_lead_in(s, lead_in_s) for s in scenarios] if lead_in_s > 0 else []
    both = simulate(scenarios + leads)
    is_lead = pc.ends_with(both["run_id"], LEAD_IN_SUFFIX)
    runs = both.filter(pc.invert(is_lead))
    profiles = {s.run_id: catalogue_profile(entry, s.vehicle) for s, entry in drawn}
    e = estimates_on_runs(load_estimator("pmf"), runs, profiles, lead_ins=both.filter(is_lead) if leads else None)
    manoeuvre = {s.run_id: s.manoeuvre for s in scenarios}
    of_sample = np.array([manoeuvre[r] for r in e["run_id"]])
    slippery = (e["mu"] >= 0.4) & (e["mu_upper"] < 0.4)
    print(f"{split}, lead-in {lead_in_s:.0f} s: {int(slippery.sum())} samples of roads >= 0.4 read below 0.4")
    print(dict(collections.Counter(of_sample[slippery].tolist())))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]))
