"""The physics estimators by name: Kalman filters on a vehicle + Dugoff tire model (docs/ESTIMATORS.md).

They need no training data, only the vehicle profile (CONTRACTS 3.2), given per call (`start(vehicle)`,
`estimate_batch(..., vehicle)`) or once here as the default for calls that pass none.
"""

from __future__ import annotations

from roadgrip.estimators.ekf import EKFEstimator
from roadgrip.estimators.kalman import KalmanEstimator
from roadgrip.estimators.ukf import UKFEstimator
from roadgrip.estimators.vehicle_model import FilterTuning
from roadgrip.vehicle.params import VehicleParams

PHYSICS_ESTIMATORS: dict[str, type[KalmanEstimator]] = {"ekf": EKFEstimator, "ukf": UKFEstimator}


def physics_estimator(
    name: str, vehicle: VehicleParams | None = None, tuning: FilterTuning | None = None
) -> KalmanEstimator:
    """The physics estimator `name` ('ekf' or 'ukf'); `vehicle` is the profile used when a call passes none (default:
    the paper's SUV), `tuning` its noise settings (default: FilterTuning())."""
    if name not in PHYSICS_ESTIMATORS:
        raise ValueError(f"physics estimator name must be one of {sorted(PHYSICS_ESTIMATORS)}, got {name!r}")
    return PHYSICS_ESTIMATORS[name](tuning=tuning, vehicle=vehicle)
