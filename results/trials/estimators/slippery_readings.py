"""Samples of roads of 0.4 and more that pmf reads with mu_upper below 0.4 (a false slippery reading), by manoeuvre and
by run, on a physics benchmark split, for a car seen for the first time or after a calm lead-in (docs/RESULTS.md, "This
release: the test split's one look").

    python results/trials/estimators/slippery_readings.py validation 0      # a fresh car, the base channels
    python results/trials/estimators/slippery_readings.py test 180          # after 180 s of calm driving (once)
    python results/trials/estimators/slippery_readings.py validation 180 all   # another channel set (base: the default)
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.evaluation.physics_benchmark import simulate_split


def main(split: str, lead_in_s: float, channels: str | None = None) -> None:
    simulated = simulate_split(split, channels=(channels,) if channels else None, lead_in_s=lead_in_s)
    runs, lead_ins = simulated.tables[channels]
    e = estimates_on_runs(load_estimator("pmf"), runs, simulated.profiles, lead_ins=lead_ins)
    of_sample = np.array([simulated.manoeuvres[r] for r in e["run_id"]])
    slippery = (e["mu"] >= 0.4) & (e["mu_upper"] < 0.4)
    print(
        f"{split}, lead-in {lead_in_s:.0f} s, channels {channels or 'base'}: {int(slippery.sum())} samples of roads >= 0.4 "
        "read below 0.4"
    )
    print(dict(collections.Counter(of_sample[slippery].tolist())))
    scenarios = {s.run_id: s for s, _ in simulated.drawn}
    for run_id, n in collections.Counter(e["run_id"][slippery].tolist()).most_common():
        k = slippery & (e["run_id"] == run_id)
        s = scenarios[run_id]
        print(
            f"  {run_id}: {n} samples, {s.manoeuvre} on {s.condition} of mu {e['mu'][k].mean():.2f}, "
            f"{type(s.tire).__name__} stiffness {s.tire.stiffness_scale:.2f}, {s.vehicle.drive}; "
            f"mu_upper down to {e['mu_upper'][k].min():.2f}"
        )


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), *sys.argv[3:4])
