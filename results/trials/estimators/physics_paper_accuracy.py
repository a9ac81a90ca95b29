"""Accuracy of the physics estimators (EKF, UKF) on the paper preset's second experiments, per condition, beside the
shipped learned model and their inverse-variance fusion; optionally on runs of the random preset, per manoeuvre.

Run: python results/trials/estimators/physics_paper_accuracy.py [--seed 0] [--random 40 --random-seed 1]
(prints the tables of docs/ESTIMATORS.md)

Per group: RMSE and MAE (eq. 14) over all samples and over the excited samples of CONTRACTS 4 (docs/CONTRACTS.md) (true utilization
sqrt(ax^2 + ay^2) / (mu g) >= 0.5, or ABS active); the coverage of the 90 % interval; the share of samples each
estimator judged excited, and how often that agrees with CONTRACTS 4's truth. The paper groups are the five conditions
(two runs each: straight and circular road, experiment 2, which the default model never trained on). The learned
model's first estimate of a run comes at its 10th sample, so every estimator is scored on the samples from the 10th on
(391 of 400 per run).
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from roadgrip.estimators.excitation import excited
from roadgrip.estimators.fusion import FusionEstimator
from roadgrip.estimators.learned import load_estimator
from roadgrip.estimators.physics import physics_estimator
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.sim.presets import PAPER_CONDITIONS, paper_scenarios, random_scenarios
from roadgrip.sim.simulate import simulate


def score(scenarios, group_of, estimators, skip: int) -> dict:
    """{estimator: {group: [per-run arrays]}} for the scenarios, each run with its own vehicle profile."""
    table = simulate(scenarios)
    run_ids = table["run_id"].to_numpy(zero_copy_only=False)
    rows = {name: {} for name in estimators}
    for scenario in scenarios:
        run = table.filter(run_ids == scenario.run_id)
        truth = run["mu"].to_numpy()
        true_excited = excited(
            run["ax_true_mps2"].to_numpy(),
            run["ay_true_mps2"].to_numpy(),
            run["abs_active"].to_numpy(zero_copy_only=False),
            truth,
        )
        ts = run["timestamp_ms"].to_numpy()
        for name, estimator in estimators.items():
            out = estimator.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), scenario.vehicle)
            index = np.searchsorted(ts, out["timestamp_ms"].to_numpy())
            keep = index >= skip
            rows[name].setdefault(group_of(scenario), []).append(
                {
                    "mu": out["mu"].to_numpy()[keep],
                    "lower": out["mu_lower"].to_numpy()[keep],
                    "upper": out["mu_upper"].to_numpy()[keep],
                    "excited": out["excited"].to_numpy()[keep],
                    "truth": truth[index[keep]],
                    "true_excited": true_excited[index[keep]],
                }
            )
    return rows


def print_table(rows: dict, groups: list[str], label: str) -> None:
    print(
        f"| estimator | {label} | RMSE all | MAE all | RMSE excited | MAE excited | excited (truth) | "
        "judged excited | agreement | 90 % coverage |"
    )
    print("| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for name, by_group in rows.items():
        for group in [*groups, "all"]:
            parts = by_group[group] if group != "all" else [p for g in groups for p in by_group[g]]
            cat = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
            ex = cat["true_excited"]
            covered = (cat["lower"] <= cat["truth"]) & (cat["truth"] <= cat["upper"])
            ex_cells = (
                f"{rmse(cat['mu'][ex], cat['truth'][ex]):.3f} | {mae(cat['mu'][ex], cat['truth'][ex]):.3f}"
                if ex.any()
                else "- | -"
            )
            print(
                f"| {name} | {group} | {rmse(cat['mu'], cat['truth']):.3f} | {mae(cat['mu'], cat['truth']):.3f} "
                f"| {ex_cells} | {ex.mean():.2f} | {cat['excited'].mean():.2f} | "
                f"{(cat['excited'] == ex).mean():.2f} | {covered.mean():.2f} |"
            )
    print()


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seed", type=int, default=0, help="paper preset seed (default 0: the default model's data)")
    parser.add_argument("--random", type=int, default=0, help="also score this many runs of the random preset")
    parser.add_argument("--random-seed", type=int, default=1, help="random preset seed (default 1)")
    args = parser.parse_args()
    torch.set_num_threads(1)  # sample-by-sample windows: threads only contend
    learned = load_estimator("default")
    estimators = {
        "ekf": physics_estimator("ekf"),
        "ukf": physics_estimator("ukf"),
        "learned": learned,
        "fusion (ekf + learned)": FusionEstimator(physics_estimator("ekf"), learned),
    }
    paper = [s for s in paper_scenarios(args.seed) if s.experiment == 2]
    print(f"paper preset, seed {args.seed}, experiment 2 (verification), vehicle {paper[0].vehicle.name}\n")
    print_table(
        score(paper, lambda s: s.condition, estimators, learned.window - 1), list(PAPER_CONDITIONS), "condition"
    )
    if args.random:
        runs = random_scenarios(args.random, seed=args.random_seed)
        manoeuvres = list(dict.fromkeys(sorted(s.manoeuvre for s in runs)))
        print(f"random preset, seed {args.random_seed}, {args.random} runs (their own vehicles and tire models)\n")
        print_table(score(runs, lambda s: s.manoeuvre, estimators, learned.window - 1), manoeuvres, "manoeuvre")


if __name__ == "__main__":
    main()
