"""pmf's braking term on stops it was not tuned on: cars drawn around the three catalogue entries, each drive layout,
their static front load share 0.06 off the catalogue's either way and 10 % heavier, drive 40 s at 20 m/s, make three
gentle stops to 16 m/s on dry asphalt (1.3 m/s^2: the braking line's calibration), and at 120 s brake to 14 m/s on a
road of mu with their first axle (by the catalogue's geometry) at a share of its limit; Dugoff and Magic Formula
tires, every production effect on, the estimator given the catalogue profile. Prints, per stop, the median over its
last second, the lowest upper end and the 90 % interval's coverage of the truth over the stop.

    nice -n 19 python results/trials/estimators/braking_term.py > out.txt

Run it from two trees (PYTHONPATH) to compare versions; braking_term.md holds the comparison of this commit with main
before the term (dc61e08). About 3 minutes on one core."""

import numpy as np

from roadgrip.estimators import pmf
from roadgrip.evaluation.bins import catalogue_profile
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires.dugoff import DugoffTire
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

STOP_AT_S = 120.0
STOPS = ((0.9, 0.85), (0.9, 0.5), (0.5, 0.5), (0.5, 0.8), (0.2, 0.8), (0.2, 0.9))  # (mu, first axle's share of it)


def speed_profile(brake_s):
    t, v = [0.0, 40.0], [20.0, 20.0]
    for _ in range(3):
        t += [t[-1] + 3.0, t[-1] + 7.0, t[-1] + 13.0]
        v += [16.0, 20.0, 20.0]
    t += [STOP_AT_S, STOP_AT_S + brake_s, STOP_AT_S + brake_s + 10.0]
    v += [20.0, 14.0, 14.0]
    return SpeedProfile(t, v), float(np.trapezoid(v[:-2], t[:-2]))


def main() -> None:
    for entry_name, entry in (("suv", PAPER_SUV), ("hatch", COMPACT_HATCHBACK), ("sedan", MIDSIZE_SEDAN)):
        for drive in ("fwd", "rwd", "awd"):
            catalogue = entry.replace(drive=drive, front_drive_share={"fwd": 1.0, "rwd": 0.0, "awd": 0.5}[drive])
            psi0 = catalogue.cg_to_rear_axle_m / catalogue.wheelbase_m
            for front_load in (-0.06, 0.06):
                car = catalogue.replace(
                    name="drawn",
                    mass_kg=1.1 * catalogue.mass_kg,
                    cg_to_front_axle_m=(1.0 - (psi0 + front_load)) * catalogue.wheelbase_m,
                )
                profile = catalogue_profile(catalogue, car)
                for tire_name, tire in (("dugoff", DugoffTire()), ("mf", MagicFormulaTire())):
                    for mu, share_of_limit in STOPS:
                        s = catalogue.brake_front_share
                        decel = share_of_limit * mu / max(s / psi0, (1 - s) / (1 - psi0)) * G_MPS2
                        brake_s = 6.0 / decel
                        speed, before = speed_profile(brake_s)
                        run = simulate(
                            [
                                Scenario(
                                    run_id="stop",
                                    path=Path.straight(4000.0),
                                    mu=MuProfile([0.0, before - 30.0], [0.9, mu], [0.9, mu]),
                                    speed=speed,
                                    vehicle=car,
                                    tire=tire,
                                    duration_s=round(STOP_AT_S + brake_s + 6.0, 1),
                                    seed=5,
                                    effects=ProductionEffects.production(),
                                )
                            ]
                        )
                        out = pmf.PMFEstimator().estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), profile)
                        t = (out["timestamp_ms"].to_numpy() - out["timestamp_ms"].to_numpy()[0]) / 1000.0
                        sel = (t > STOP_AT_S) & (t < STOP_AT_S + brake_s)
                        m, lo, up = (out[k].to_numpy()[sel] for k in ("mu", "mu_lower", "mu_upper"))
                        print(
                            entry_name,
                            drive,
                            front_load,
                            tire_name,
                            mu,
                            share_of_limit,
                            f"med_end {np.median(m[-10:]):.2f} up_min {up.min():.2f} "
                            f"cov {((lo <= mu) & (up >= mu)).mean():.2f}",
                            flush=True,
                        )


if __name__ == "__main__":
    main()
