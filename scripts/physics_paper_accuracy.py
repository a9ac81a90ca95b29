"""Accuracy of the physics estimators (EKF, UKF) on the paper preset's second experiments, per condition, beside the
shipped learned model and their inverse-variance fusion.

Run: python scripts/physics_paper_accuracy.py [--seed 0]   (prints the tables of docs/ESTIMATORS.md)

For each condition (two runs each: straight and circular road, experiment 2, never used for training the default
model): RMSE and MAE (eq. 14) over all samples and over the excited samples of DESIGN 4 (true utilization
sqrt(ax^2 + ay^2) / (mu g) >= 0.5, or ABS active); the coverage of the 90 % interval; the share of samples each
estimator judged excited, and how often it agrees with DESIGN 4's truth. The learned model's first estimate of a run
comes at its 10th sample, so every estimator is scored on the samples from the 10th on (391 of 400 per run).
"""

from __future__ import annotations

import argparse

import numpy as np

from roadgrip.estimators.excitation import excited
from roadgrip.estimators.fusion import FusionEstimator
from roadgrip.estimators.learned import load_estimator
from roadgrip.estimators.physics import physics_estimator
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.sim.presets import PAPER_CONDITIONS, paper_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0, help="paper preset seed (default 0: the default model's data)")
    args = parser.parse_args()
    scenarios = [s for s in paper_scenarios(args.seed) if s.experiment == 2]
    table = simulate(scenarios)
    learned = load_estimator("default")
    estimators = {"ekf": physics_estimator("ekf"), "ukf": physics_estimator("ukf"), "learned": learned,
                  "fusion (ekf + learned)": FusionEstimator(physics_estimator("ekf"), learned)}
    rows = {name: {c: [] for c in PAPER_CONDITIONS} for name in estimators}
    run_ids = table["run_id"].to_numpy(zero_copy_only=False)
    for scenario in scenarios:
        run = table.filter(run_ids == scenario.run_id)
        truth = run["mu"].to_numpy()
        true_excited = excited(run["ax_true_mps2"].to_numpy(), run["ay_true_mps2"].to_numpy(),
                               run["abs_active"].to_numpy(zero_copy_only=False), truth)
        ts = run["timestamp_ms"].to_numpy()
        for name, estimator in estimators.items():
            out = estimator.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), PAPER_SUV)
            index = np.searchsorted(ts, out["timestamp_ms"].to_numpy())
            keep = index >= learned.window - 1
            rows[name][scenario.condition].append({
                "mu": out["mu"].to_numpy()[keep], "lower": out["mu_lower"].to_numpy()[keep],
                "upper": out["mu_upper"].to_numpy()[keep], "excited": out["excited"].to_numpy()[keep],
                "truth": truth[index[keep]], "true_excited": true_excited[index[keep]],
            })
    print(f"paper preset, seed {args.seed}, experiment 2 (verification), vehicle {PAPER_SUV.name}\n")
    print("| estimator | condition | RMSE all | MAE all | RMSE excited | MAE excited | excited (truth) | "
          "judged excited | agreement | 90 % coverage |")
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name in estimators:
        for condition in [*PAPER_CONDITIONS, "all"]:
            parts = rows[name][condition] if condition != "all" else [p for c in PAPER_CONDITIONS
                                                                        for p in rows[name][c]]
            cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            ex = cat["true_excited"]
            covered = (cat["lower"] <= cat["truth"]) & (cat["truth"] <= cat["upper"])
            ex_cells = (f"{rmse(cat['mu'][ex], cat['truth'][ex]):.3f} | {mae(cat['mu'][ex], cat['truth'][ex]):.3f}"
                        if ex.any() else "- | -")
            print(f"| {name} | {condition} | {rmse(cat['mu'], cat['truth']):.3f} | {mae(cat['mu'], cat['truth']):.3f} "
                  f"| {ex_cells} | {ex.mean():.2f} | {cat['excited'].mean():.2f} | "
                  f"{(cat['excited'] == ex).mean():.2f} | {covered.mean():.2f} |")


if __name__ == "__main__":
    main()
