"""Every estimator by true utilization bin on simulated runs with the production-terminal effects on.

python results/trials/production/estimator_bins.py                       # the generalization benchmark's held-out test runs, seed 0
python results/trials/production/estimator_bins.py --random 40 --seed 11  # 40 runs of the random preset (vehicles around the sedan
                                                        # and the SUV, stiffer tires), seed 11
"""

from __future__ import annotations

import argparse
import time

from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.bins import (
    BIN_ESTIMATORS,
    bins_markdown,
    estimates_on_runs,
    estimator_bins,
    run_bins_benchmark,
)
from roadgrip.sim.presets import random_scenarios
from roadgrip.sim.simulate import simulate


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--random", type=int, default=0, help="runs of the random preset instead of the test runs")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--estimators", default=",".join(BIN_ESTIMATORS))
    args = parser.parse_args()
    names = args.estimators.split(",")
    start = time.perf_counter()
    if args.random:
        scenarios = random_scenarios(args.random, args.seed)
        table = simulate(scenarios)
        vehicles = {s.run_id: s.vehicle for s in scenarios}
        rows = [
            {"estimator": name} | row
            for name in names
            for row in estimator_bins(estimates_on_runs(load_estimator(name), table, vehicles))
        ]
    else:
        rows = run_bins_benchmark(args.seed, names)
    print(bins_markdown(rows))
    print(f"{time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
