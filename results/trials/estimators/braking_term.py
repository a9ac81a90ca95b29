"""pmf's braking term on stops it was not tuned on: cars drawn around the three catalogue entries, each drive layout,
their static front load share 0.06 off the catalogue's either way and 10 % heavier, every production effect on, the
estimator given the catalogue profile. Each drives the test's stop (tests/estimators/test_pmf_braking.py,
`stop_estimates`: 40 s at 20 m/s, three gentle stops to 16 m/s on dry asphalt, the braking line's calibration, then at
120 s a stop to 14 m/s on a road of mu with the first axle, by the catalogue's geometry, at a share of its limit), on
Dugoff and Magic Formula tires. Prints, per stop, the median over its last second, the lowest upper end and the 90 %
interval's coverage of the truth over the stop. Run from the repository root:

    nice -n 19 python results/trials/estimators/braking_term.py > out.txt

Run it from two trees (PYTHONPATH) to compare versions; braking_term.md holds the comparison of the term with main
before it (dc61e08). About 3 minutes on one core."""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests" / "estimators"))  # the repository root
from test_pmf_braking import DRIVES, TIRES, drawn_car, stop_estimates  # the test's stop: one description of it

from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV

STOPS = ((0.95, 0.85), (0.95, 0.5), (0.5, 0.5), (0.5, 0.8), (0.2, 0.8), (0.2, 0.9))  # (mu, first axle's share of it)

for entry_name, entry in (("suv", PAPER_SUV), ("hatch", COMPACT_HATCHBACK), ("sedan", MIDSIZE_SEDAN)):
    for drive in DRIVES:
        for front_load in (-0.06, 0.06):
            car, catalogue = drawn_car(entry, drive, front_load)
            for tire in TIRES:
                for mu, share_of_limit in STOPS:
                    est = stop_estimates(car, catalogue, TIRES[tire], mu, share_of_limit)
                    lo, up = est["mu_lower"], est["mu_upper"]
                    print(
                        entry_name,
                        drive,
                        front_load,
                        tire,
                        mu,
                        share_of_limit,
                        f"med_end {np.median(est['mu'][-10:]):.2f} up_min {up.min():.2f} "
                        f"cov {((lo <= mu) & (up >= mu)).mean():.2f}",
                        flush=True,
                    )
