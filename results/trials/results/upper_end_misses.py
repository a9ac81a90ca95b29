"""How often the truth lies above pmf's upper end, on the physics benchmark's validation split: the size of the friction
map's outlier_rate (roadgrip/cloud/domain/friction_map.py; docs/RESULTS.md, "The map's trust in an upper end").

Among the samples whose mu_upper is below 1.2 (the upper ends the map reads; 1.2 is "nothing known above"), by the
upper end's value: the share with the true mu above it. A 90 % interval's upper end should be below the truth on 0.05.
A car seen for the first time, and after 180 s of calm driving (the benchmark's --lead-in-s).

    python results/trials/results/upper_end_misses.py
"""

import numpy as np

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.evaluation.physics_benchmark import simulate_split

BANDS = ((0.0, 0.6), (0.6, 0.8), (0.8, 1.0), (1.0, 1.1), (1.1, 1.2))


def main() -> None:
    split = simulate_split("validation", lead_in_s=180.0)
    runs, leads = split.tables[None]
    for name, lead_ins in (("fresh", None), ("after 180 s", leads)):
        e = estimates_on_runs(load_estimator("pmf"), runs, split.profiles, lead_ins=lead_ins)
        upper, mu = e["mu_upper"], e["mu"]
        read = upper < 1.2
        print(f"{name}: upper ends below 1.2 {read.sum()}, truth above {np.mean(mu[read] > upper[read]):.3f}")
        for lo, hi in BANDS:
            m = (upper >= lo) & (upper < hi)
            print(f"  upper in [{lo}, {hi}): {m.sum():6d} samples, truth above {np.mean(mu[m] > upper[m]):.3f}")


if __name__ == "__main__":
    main()
