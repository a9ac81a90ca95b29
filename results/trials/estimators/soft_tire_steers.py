"""The lateral drives of tests/estimators (lateral_drives.py, test split: ramp and sine steers on ice or dry asphalt)
on tires of another stiffness scale, fresh or after the calm drive on tires FACTOR times as stiff (another surface):
per run the lowest mu_upper, and at true utilization 0.5-0.9 the coverage and the share of mu_upper below 0.45
(docs/RESULTS.md, "A new road's cornering slope").

    python results/trials/estimators/soft_tire_steers.py FACTOR dry|ice SCALE    # FACTOR 0: a fresh state
"""

import dataclasses
import sys

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

sys.path.insert(0, "tests/estimators")
from lateral_drives import calm_drive, scenarios

from roadgrip.estimators.pmf import PMFEstimator
from roadgrip.evaluation.bins import true_utilization
from roadgrip.sim.simulate import simulate


def main(factor: float, dry: bool, scale: float) -> None:
    runs = [
        s.replace(tire=dataclasses.replace(s.tire, stiffness_scale=scale))
        for s in scenarios("test")
        if (s.mu.mu_left[0] > 0.5) == dry
    ]
    calms = [
        calm_drive(s).replace(tire=dataclasses.replace(s.tire, stiffness_scale=scale * max(factor, 1.0))) for s in runs
    ]
    table = simulate(runs + calms)
    estimator = PMFEstimator()
    covered, low = [], []
    for s in runs:
        run = table.filter(pc.equal(table["run_id"], s.run_id))
        calm = table.filter(pc.equal(table["run_id"], f"calm-{s.run_id}")).slice(0, None if factor > 0 else 0)
        rows = pa.concat_tables([calm, run])
        segments = np.repeat([0, 1], [calm.num_rows, run.num_rows])
        out = estimator.estimate_batch(rows, segments, s.vehicle).slice(calm.num_rows)
        mu = run["mu"].to_numpy()
        u = true_utilization(run["ax_true_mps2"].to_numpy(), run["ay_true_mps2"].to_numpy(), mu)
        lower, upper = out["mu_lower"].to_numpy(), out["mu_upper"].to_numpy()
        working = (u >= 0.5) & (u < 0.9)
        covered.append(((lower <= mu) & (mu <= upper))[working])
        low.append(upper[working] < 0.45)
        print(
            f"{s.run_id}: lowest mu_upper {upper.min():.2f}, at u 0.5-0.9 coverage {covered[-1].mean():.2f}, "
            f"mu_upper < 0.45 {low[-1].mean():.2f}"
        )
    print(f"pooled: coverage {np.concatenate(covered).mean():.3f}, mu_upper < 0.45 {np.concatenate(low).mean():.3f}")


if __name__ == "__main__":
    main(float(sys.argv[1]), sys.argv[2] == "dry", float(sys.argv[3]))
