"""How much of the paper benchmark's ranking is training noise? The benchmark repeated with several training seeds on
the same data (simulated with seed 0): mean and spread of each RMSE, and the acceptance count per seed.

Run: python results/trials/results/paper_seeds.py [n_seeds]   (default 3; about 4 min per seed on 2 cores; quoted in docs/RESULTS.md)
"""

import sys
from collections import defaultdict

import numpy as np

from roadgrip.evaluation.paper import run_paper_benchmark
from roadgrip.evaluation.report import summary_rows
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate


def main(n_seeds: int = 3):
    table = simulate(paper_scenarios(seed=0))
    rmses = defaultdict(list)
    for seed in range(n_seeds):
        metrics, _ = run_paper_benchmark(table, seed=seed)
        for row in metrics:
            rmses[(row["trained_on"], row["feature_set"], row["condition"], row["model"])].append(row["rmse"])
        for s in summary_rows(metrics):
            if s["source"] == "ours":
                print(
                    f"seed {seed}: trained on {s['trained_on']:9s} {s['feature_set']:8s} SA-CNN-LSTM beats all three "
                    f"on {s['wins_all']} of {s['compared']}",
                    flush=True,
                )
    print("\n| trained on | features | condition | model | RMSE mean | RMSE min | RMSE max |")
    print("| --- | --- | --- | --- | ---: | ---: | ---: |")
    for (scope, fs, condition, model), values in sorted(rmses.items()):
        print(
            f"| {scope} | {fs} | {condition} | {model} | {np.mean(values):.3f} | {np.min(values):.3f} | "
            f"{np.max(values):.3f} |"
        )


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:2]))
