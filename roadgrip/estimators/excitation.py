"""When is mu observable? CONTRACTS 4: a sample is excited when the tires use at least half of the available friction,
sqrt(a_x^2 + a_y^2) / (mu g) >= 0.5, or when ABS acts. Under steadier driving a tire's force hardly depends on mu (in
Dugoff's linear region not at all), so no estimator can read mu from the car's motion there."""

import numpy as np

from roadgrip.units import G_MPS2

EXCITATION_UTILIZATION = 0.5


def excited(accel_lon_mps2, accel_lat_mps2, abs_active, mu) -> np.ndarray:
    """Excitation per sample; with estimated rather than true mu it is an estimator's own judgement."""
    utilization = np.hypot(accel_lon_mps2, accel_lat_mps2) / (np.maximum(mu, 0.05) * G_MPS2)
    return (utilization >= EXCITATION_UTILIZATION) | np.asarray(abs_active, dtype=bool)
