"""Does a tire whose force falls past its peak make pmf's interval miss a dry road under ABS? (The physics test
split's look of 2026-12-07: ABS on mu >= 0.6 covers 0.50 there, on validation 0.98; Burckhardt's curves fall past
the peak, c3.) Magic Formula tires of shape factor 1.65 and 1.9 (sliding at 0.52 and 0.16 of the peak; Burckhardt's
dry asphalt 0.65) against the default 1.4, the last also half as stiff, on the validation split's vehicles with their
catalogue profiles, every production effect on: ABS stops from 25 m/s asking 1.3 mu g at mu 0.8, 1.0 and 1.15.
Printed per run: the share of samples with ABS acting, the 90 % interval's coverage over them, the lowest mu_upper.

    PYTHONPATH=<checkout> nice -n 19 python results/trials/estimators/abs_falling_branch.py
"""

from roadgrip.estimators.pmf import PMFEstimator
from roadgrip.evaluation.bins import estimates_on_runs
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, PAPER_SUV
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

RUN = {"duration_s": 12.0, "seed": 3, "effects": ProductionEffects.production()}


def main():
    tires = (
        MagicFormulaTire(),
        MagicFormulaTire(shape_c=1.65),
        MagicFormulaTire(shape_c=1.9),
        MagicFormulaTire(shape_c=1.9, stiffness_scale=0.5),
    )
    for tire in tires:
        for vehicle in (PAPER_SUV, COMPACT_HATCHBACK):
            for mu in (0.8, 1.0, 1.15):
                ramp = 25.0 / (1.3 * mu * G_MPS2)
                speed = SpeedProfile([0.0, 3.0, 3.0 + ramp, 20.0], [25.0, 25.0, 0.0, 0.0])
                road = (Path.straight(1500.0), MuProfile.uniform(mu), speed)
                scenario = Scenario("abs", *road, vehicle=vehicle, tire=tire, **RUN)
                e = estimates_on_runs(PMFEstimator(), simulate([scenario]), {"abs": vehicle})
                on = e["abs_active"].astype(bool)
                covered = (e["mu_lower"] <= mu) & (e["mu_upper"] >= mu)
                print(
                    f"C {tire.shape_c} x{tire.stiffness_scale} {vehicle.name} mu {mu}: ABS {on.mean():.2f}, "
                    f"coverage under ABS {covered[on].mean():.2f}, lowest mu_upper {e['mu_upper'].min():.2f}"
                )


if __name__ == "__main__":
    main()
