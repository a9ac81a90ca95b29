"""Where a degraded GNSS speed (ChannelModel.degraded_gnss: latency 0.2 s, 10 % outages, 5 % multipath outliers) makes
pmf worse than the base channels on the physics benchmark's validation split (issue 26: "no worse than base channels
anywhere"): for one manoeuvre and mu band, the runs whose squared error grows most from [base] to [gnss-degraded], and
within them the samples by phase (ABS acting, braking, accelerating, steady), with [gnss] (a clean receiver) beside.

    python results/trials/estimators/gnss_degraded_against_base.py braking_abs 0.3-0.6
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.evaluation.physics_benchmark import mu_band, simulate_split

SETS = ("base", "gnss", "gnss-degraded")


def phase(e, i) -> str:
    if e["abs_active"][i]:
        return "ABS"
    ax = e["ax_true_mps2"][i]
    return "braking" if ax < -0.5 else "accelerating" if ax > 0.5 else "steady"


def main(manoeuvre: str, band: str) -> None:
    split = simulate_split("validation", channels=SETS)
    est = {s: estimates_on_runs(load_estimator("pmf"), split.tables[s][0], split.profiles) for s in SETS}
    e = est["base"]
    of_run = np.array([split.manoeuvres[r] for r in e["run_id"]])
    chosen = (of_run == manoeuvre) & (mu_band(e["mu"]) == band)
    sq = {s: (est[s]["mu_est"] - e["mu"]) ** 2 for s in SETS}
    print(
        f"{manoeuvre}, mu {band}: {chosen.sum()} samples, RMSE "
        + ", ".join(f"[{s}] {np.sqrt(sq[s][chosen].mean()):.3f}" for s in SETS)
    )
    by_phase = collections.defaultdict(list)
    for i in np.nonzero(chosen)[0]:
        by_phase[phase(e, i)].append(i)
    for name, rows in sorted(by_phase.items()):
        k = np.array(rows)
        print(f"  {name}: {k.size} samples, RMSE " + ", ".join(f"[{s}] {np.sqrt(sq[s][k].mean()):.3f}" for s in SETS))
    growth = collections.Counter()
    for i in np.nonzero(chosen)[0]:
        growth[e["run_id"][i]] += sq["gnss-degraded"][i] - sq["base"][i]
    for run_id, g in growth.most_common(6):
        k = np.nonzero(e["run_id"] == run_id)[0]
        print(
            f"  {run_id}: squared error summed +{g:.2f}, mu {e['mu'][k].mean():.2f}; median estimate "
            + ", ".join(f"[{s}] {np.median(est[s]['mu_est'][k]):.2f}" for s in SETS)
        )


if __name__ == "__main__":
    main(sys.argv[1], sys.argv[2])
