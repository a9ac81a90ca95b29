"""Where pmf's upper end lies below the truth on the physics benchmark's validation split, a car seen for the first
time, one channel set: among the samples whose mu_upper is below 1.2, the misses by manoeuvre, tire model, stiffness
(soft: below 0.7 of the catalogue's) and mu band, and the runs with the most (docs/RESULTS.md, "The lateral
accelerometer's bias counted once").

    python results/trials/estimators/upper_end_misses_by_run.py base      # or gnss, forces, steering, all
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.guard import PRIOR_UPPER_MU
from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.evaluation.physics_benchmark import mu_band, simulate_split


def main(channels: str) -> None:
    split = simulate_split("validation", channels=(channels,))
    scenarios = {s.run_id: s for s, _ in split.drawn}
    e = estimates_on_runs(load_estimator("pmf"), split.tables[channels][0], split.profiles)
    upper, mu, run_id = e["mu_upper"], e["mu"], e["run_id"]
    read = upper < PRIOR_UPPER_MU  # 1.2: nothing known above
    miss = read & (mu > upper)
    bands = mu_band(mu)
    print(
        f"mu_upper below 1.2 on {read.sum()} samples, the truth above it on {miss.sum()} ({miss.mean() / read.mean():.3f})"
    )
    groups, excess, per_run = collections.Counter(), collections.Counter(), collections.Counter()
    for i in np.nonzero(miss)[0]:
        s = scenarios[run_id[i]]
        key = (
            s.manoeuvre,
            type(s.tire).__name__,
            "soft" if s.tire.stiffness_scale < 0.7 else "other",
            f"mu {bands[i]}",
        )
        groups[key] += 1
        excess[key] += mu[i] - upper[i]
        per_run[run_id[i]] += 1
    for key, n in groups.most_common():
        print(f"  {' / '.join(key)}: {n} misses, the truth {excess[key] / n:.3f} above mu_upper on average")
    for rid, n in per_run.most_common(10):
        s = scenarios[rid]
        print(f"  {rid}: {n} misses, {s.manoeuvre}, {type(s.tire).__name__} at {s.tire.stiffness_scale:.2f}")


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "base")
