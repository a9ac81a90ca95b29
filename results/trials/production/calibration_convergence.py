"""How fast pmf's self-calibration converges on ordinary driving: a FWD car driven gently (0 to 0.09 g) for ten
minutes on a worn tire (half the profile's slip stiffness), its front tires 1 % fuller than the rear and the front left
2 % fuller than the front right, its accelerometer 0.6 m/s^2 off. Prints the error of each calibration minute by minute
(a Markdown table; docs/PRODUCTION.md). Run from the repository root:
python results/trials/production/calibration_convergence.py"""

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[3] / "tests" / "estimators"))  # the repository root
from test_pmf import FWD, worn_tire_drive  # the test's drive: one description of it

from roadgrip.estimators.pmf import PMFEstimator

samples, c = worn_tire_drive(6000)
estimator = PMFEstimator()
state = estimator.start(FWD)
km = 0.0
print("| driven | km | bias error (m/s^2) | left/right ratio error | front/rear offset error | stiffness error |")
print("|---|---|---|---|---|---|")
for k, sample in enumerate(samples):
    estimator.update(state, sample)
    km += sample["speed_mps"] * 0.1 / 1000
    if (k + 1) % 600 == 0:
        cal = estimator.calibration(state)
        print(
            f"| {(k + 1) / 600:.0f} min | {km:.1f} | {cal['accel_bias_mps2'] + 0.6:+.3f} | "
            f"{cal['radius_ratio_left_right_front'] - 0.02:+.4f} | {cal['slip_offset_front_rear'] - 0.01:+.4f} | "
            f"{1 / cal['slip_slope'] / c - 1:+.1%} |"
        )
