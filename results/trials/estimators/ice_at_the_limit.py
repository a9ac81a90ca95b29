"""Where pmf's largest error lies: ice and snow (mu <= 0.3) with the tires at 0.8 of their limit and more (the true
utilization; ABS samples are their own bin), on the physics benchmark's validation split, by manoeuvre, tire model and
drive: samples, runs, RMSE, the mean estimate and the median interval (docs/RESULTS.md, "What the forgetting redraws
at the limit").

    python results/trials/estimators/ice_at_the_limit.py base 0       # a fresh car; or all, and 180 (a calm lead-in)
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs, true_utilization
from roadgrip.evaluation.physics_benchmark import simulate_split


def main(channels: str, lead_in_s: float) -> None:
    split = simulate_split("validation", channels=(channels,), lead_in_s=lead_in_s)
    runs, lead_ins = split.tables[channels]
    e = estimates_on_runs(load_estimator("pmf"), runs, split.profiles, lead_ins=lead_ins)
    u = true_utilization(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"])
    chosen = (e["mu"] <= 0.3) & (u >= 0.8) & ~e["abs_active"].astype(bool)
    error = e["mu_est"] - e["mu"]
    print(
        f"{channels}, lead-in {lead_in_s:.0f} s: {chosen.sum()} samples of mu <= 0.3 at u >= 0.8 (not ABS), "
        f"RMSE {np.sqrt((error[chosen] ** 2).mean()):.3f}"
    )
    scenario = {s.run_id: s for s, _ in split.drawn}
    groups = collections.defaultdict(list)
    for i in np.nonzero(chosen)[0]:
        s = scenario[e["run_id"][i]]
        groups[(s.manoeuvre, type(s.tire).__name__, s.vehicle.drive)].append(i)
    for key, rows in sorted(groups.items()):
        k = np.array(rows)
        print(
            f"  {' / '.join(key)}: {k.size} samples, {len(set(e['run_id'][k]))} runs, RMSE "
            f"{np.sqrt((error[k] ** 2).mean()):.3f}, estimate {e['mu_est'][k].mean():.2f} (truth {e['mu'][k].mean():.2f}), "
            f"interval [{np.median(e['mu_lower'][k]):.2f}, {np.median(e['mu_upper'][k]):.2f}]"
        )


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "base", float(sys.argv[2]) if len(sys.argv) > 2 else 0.0)
