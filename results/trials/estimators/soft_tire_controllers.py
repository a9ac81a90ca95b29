"""Do ABS and traction control read a dry or wet road as slippery on a tire with a soft slip curve? (The physics test
split's look of 2026-12-07 found 869 samples of truth >= 0.4 read with mu_upper < 0.4, mostly under the controllers;
its Burckhardt tire takes dry cobblestone's curve for mu 0.9-1.085, a third as steep as dry asphalt's.)

The physics validation split's braking and accelerating runs on roads of 0.4 and more whose tire was drawn below half
the catalogue's stiffness (the split draws 0.3-1.3 since 2026-12-07), each with the catalogue profile, every
production effect on. Printed per run: tire, stiffness scale, mu, the share of samples with the run's controller
acting, the lowest mu_upper, the 90 % interval's coverage and the count of samples with mu_upper below 0.4.

    PYTHONPATH=<checkout> nice -n 19 python results/trials/estimators/soft_tire_controllers.py
"""

import numpy as np

from roadgrip.estimators.pmf import PMFEstimator
from roadgrip.evaluation.bins import catalogue_profile
from roadgrip.sim.presets import physics_benchmark_runs
from roadgrip.sim.simulate import simulate

FLAG = {"braking_abs": "abs_active", "acceleration": "tcs_active"}


def main():
    total = 0
    for scenario, entry in physics_benchmark_runs("validation"):
        mu = float(scenario.mu.mu_left[0])
        if scenario.manoeuvre not in FLAG or mu < 0.4 or scenario.tire.stiffness_scale >= 0.5:
            continue
        run = simulate([scenario])
        profile = catalogue_profile(entry, scenario.vehicle)
        out = PMFEstimator().estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), profile)
        upper, lower = out["mu_upper"].to_numpy(), out["mu_lower"].to_numpy()
        flag = run[FLAG[scenario.manoeuvre]].to_numpy(zero_copy_only=False).astype(bool)
        slippery = int((upper < 0.4).sum())
        total += slippery
        print(
            f"{scenario.run_id} {scenario.manoeuvre} {scenario.tire.name} x{scenario.tire.stiffness_scale:.2f} "
            f"mu {mu:.2f}: controller {flag.mean():.2f}, lowest mu_upper {upper.min():.2f}, coverage "
            f"{((lower <= mu) & (upper >= mu)).mean():.2f}, mu_upper < 0.4: {slippery}"
        )
    print(f"samples with mu_upper < 0.4: {total}")


if __name__ == "__main__":
    main()
