"""How fast pmf's self-calibration converges on ordinary driving: a FWD car driven gently (0 to 0.09 g) for ten
minutes on a worn tire (half the profile's slip stiffness), its front tires 1 % fuller than the rear and the front left
2 % fuller than the front right, its accelerometer 0.6 m/s^2 off. Prints the error of each calibration minute by minute
(a Markdown table; docs/PRODUCTION.md). Run from the repository root: python scripts/calibration_convergence.py"""

import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parents[1] / "tests" / "estimators"))
from test_pmf import FWD, _samples  # noqa: E402  (the test's drive builder: one description of the drive)

from roadgrip.estimators.guard import drag_per_mass  # noqa: E402
from roadgrip.estimators.pmf import PMFEstimator  # noqa: E402
from roadgrip.units import G_MPS2  # noqa: E402

n = 6000
road = (0.04 + 0.05 * np.sin(np.arange(n) * 2 * np.pi / 200)) * G_MPS2
speed = np.empty(n)
speed[0] = 20.0
for i in range(1, n):
    speed[i] = speed[i - 1] + (road[i - 1] - drag_per_mass(FWD) * speed[i - 1] ** 2) * 0.1
fz = FWD.mass_kg * (G_MPS2 * FWD.cg_to_rear_axle_m - road * FWD.cg_height_m) / FWD.wheelbase_m
c = 0.5 * FWD.tire_front.longitudinal_stiffness_per_load
slip = 3 * 0.9 / c * (1 - np.cbrt(1 - FWD.mass_kg * road / fz / 0.9))
samples = _samples(speed, road - drag_per_mass(FWD) * speed ** 2, accel_bias=-0.6, radius_ratio=(1.02, 1.0, 1.0, 1.0),
                   front_slip=slip)
estimator = PMFEstimator()
state = estimator.start(FWD)
print("| driven | km | bias error (m/s^2) | left/right ratio error | front/rear offset error | stiffness error |")
print("|---|---|---|---|---|---|")
for k, sample in enumerate(samples):
    estimator.update(state, sample)
    if (k + 1) % 600 == 0:
        cal = estimator.calibration(state)
        km = np.sum(speed[:k + 1]) * 0.1 / 1000
        print(f"| {(k + 1) / 600:.0f} min | {km:.1f} | {cal['accel_bias_mps2'] + 0.6:+.3f} | "
              f"{cal['radius_ratio_left_right_front'] - 0.02:+.4f} | {cal['slip_offset_front_rear'] - 0.01:+.4f} | "
              f"{1 / cal['slip_slope'] / c - 1:+.1%} |")
