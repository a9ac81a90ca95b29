"""Where pmf's largest error lies: ice and snow (mu <= 0.3) with the tires at 0.8 of their limit and more (the true
utilization; ABS samples are their own bin), on the physics benchmark's validation split, by manoeuvre, tire model and
drive: samples, runs, RMSE, the mean estimate and the median interval (docs/RESULTS.md, "What the forgetting redraws
at the limit").

    python results/trials/estimators/ice_at_the_limit.py base 0       # a fresh car; or all, and 180 (a calm lead-in)
    python results/trials/estimators/ice_at_the_limit.py base 0 0.5 0.8   # another utilization bin: [0.5, 0.8)
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs, true_utilization
from roadgrip.evaluation.physics_benchmark import simulate_split


def by_group(e: dict, split, title: str, u_low: float = 0.8, u_high: float = np.inf) -> None:
    """Print the ice and snow samples (not ABS) of estimates `e` at u in [u_low, u_high), by manoeuvre, tire and drive."""
    u = true_utilization(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"])
    chosen = (e["mu"] <= 0.3) & (u >= u_low) & (u < u_high) & ~e["abs_active"].astype(bool)
    error = e["mu_est"] - e["mu"]
    print(
        f"{title}: {chosen.sum()} samples of mu <= 0.3 at u in [{u_low}, {u_high}) (not ABS), "
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


def main(channels: str, lead_in_s: float = 0.0, u_low: float = 0.8, u_high: float = np.inf) -> None:
    split = simulate_split("validation", channels=(channels,), lead_in_s=lead_in_s)
    runs, lead_ins = split.tables[channels]
    e = estimates_on_runs(load_estimator("pmf"), runs, split.profiles, lead_ins=lead_ins)
    by_group(e, split, f"{channels}, lead-in {lead_in_s:.0f} s", u_low, u_high)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "base", *(float(a) for a in sys.argv[2:5]))
