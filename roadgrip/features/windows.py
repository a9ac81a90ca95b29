"""Feature sets and windows of consecutive samples.

A window is `length` consecutive samples of one segment (a run, or a stretch of one vehicle's stream without a gap); its
label is the value at its last sample, so a model that reads a window estimates mu now from the recent past, as it must in
a live stream. Windows never cross segments: a window whose first and last samples lie in different segments is dropped.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from roadgrip.data.schema import WHEELS
from roadgrip.features.production import (
    OPTIONAL_FLAGS,
    PRODUCTION_FEATURES,
    PRODUCTION_INPUTS,
    production_features,
    vehicle_profile,  # noqa: F401  (re-exported: the profile a feature set takes)
)
from roadgrip.units import G_MPS2
from roadgrip.validation import check_choice
from roadgrip.vehicle.dynamics import SLIP_SPEED_FLOOR_MPS

WHEEL_SPEEDS = tuple(f"wheel_speed_{w}_radps" for w in WHEELS)
TERMINAL_INPUTS = (
    "speed_mps",
    "accel_lon_mps2",
    "accel_lat_mps2",
    "yaw_rate_radps",
    "steering_wheel_angle_rad",
    "abs_active",
) + WHEEL_SPEEDS
FEATURE_SETS = {
    # paper 3.3: yaw rate, longitudinal speed, lateral speed and the four wheel angular speeds
    "paper": ("yaw_rate_radps", "speed_mps", "lateral_speed_mps") + WHEEL_SPEEDS,
    # what a production terminal sends (CONTRACTS 3.1), without the lateral speed that only test vehicles measure
    "terminal": ("speed_mps", "accel_lon_mps2", "accel_lat_mps2", "yaw_rate_radps", "steering_wheel_angle_rad")
    + WHEEL_SPEEDS,
    # the terminal's signals made independent of the vehicle with its profile (CONTRACTS 3.2): slip ratios from wheel speeds
    # and radius (eq. 6), accelerations and the yaw rate's centripetal part in g, the road-wheel angle, ABS
    "physics": tuple(f"slip_ratio_{w}" for w in WHEELS)
    + ("accel_lon_g", "accel_lat_g", "centripetal_g", "road_wheel_angle_rad", "speed_mps", "abs_active"),
    # what holds on a production car, whose speed signal comes from its wheels: wheels compared with wheels, wheel
    # speed rates against the accelerometer, accelerations in g, the profile's geometry (roadgrip/features/production.py)
    "production": PRODUCTION_FEATURES,
}
PROFILE_FEATURE_SETS = {"physics", "production"}  # feature sets that need the vehicle profile


def feature_columns(feature_set: str) -> tuple[str, ...]:
    check_choice("features", "feature_set", feature_set, set(FEATURE_SETS))
    return FEATURE_SETS[feature_set]


def needs_vehicle(feature_set: str) -> bool:
    feature_columns(feature_set)
    return feature_set in PROFILE_FEATURE_SETS


def input_columns(feature_set: str) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(required, optional) telemetry columns that a feature set reads."""
    if feature_set == "production":
        return PRODUCTION_INPUTS, OPTIONAL_FLAGS
    return (TERMINAL_INPUTS if needs_vehicle(feature_set) else feature_columns(feature_set)), ()


def feature_matrix(
    table: pa.Table,
    feature_set: str,
    wheel_radius_m=None,
    steering_ratio=None,
    *,
    profile: dict | None = None,
    segments=None,
) -> np.ndarray:
    """(n_samples, n_features) float32 matrix of a feature set; a missing column is an error naming it.

    Feature sets that use the vehicle profile take it as `profile` (`vehicle_profile(vehicle)`: each field one value
    or one per row) or, for `physics`, as the wheel radius and steering ratio. `segments` (an id per sample) marks
    where a stream restarts, for the features that difference consecutive samples (`production`); None: one stream."""
    required, optional = input_columns(feature_set)
    missing = [c for c in required if c not in table.column_names]
    if missing:
        raise ValueError(f"feature set {feature_set!r} needs column(s) {missing}, which the data lacks")
    data = {c: _column(table[c]) for c in required + tuple(c for c in optional if c in table.column_names)}
    return features_from_columns(data, feature_set, wheel_radius_m, steering_ratio, profile=profile, segments=segments)


def _column(column) -> np.ndarray:
    if pa.types.is_boolean(column.type):
        column = column.fill_null(False)
    return column.to_numpy(zero_copy_only=False).astype(np.float64)


def features_from_columns(
    data: dict,
    feature_set: str,
    wheel_radius_m=None,
    steering_ratio=None,
    *,
    profile: dict | None = None,
    segments=None,
    previous: dict | None = None,
) -> np.ndarray:
    """The feature matrix from column arrays (a table's, or one streamed sample's). `previous`: for a stream fed
    sample by sample, the sample before data's first (None at the stream's start); see feature_matrix for the rest."""
    if not needs_vehicle(feature_set):
        return np.column_stack([np.asarray(data[c], dtype=np.float32) for c in feature_columns(feature_set)])
    if profile is None:
        profile = {"wheel_radius_m": wheel_radius_m, "steering_ratio": steering_ratio}
    if feature_set == "production":
        return production_features(data, profile, segments, previous)
    wheel_radius_m, steering_ratio = profile.get("wheel_radius_m"), profile.get("steering_ratio")
    if wheel_radius_m is None or steering_ratio is None:
        raise ValueError(f"feature set {feature_set!r} needs the vehicle profile (wheel_radius_m, steering_ratio)")
    speed = np.asarray(data["speed_mps"], dtype=np.float64)
    derived = {
        f"slip_ratio_{w}": slip_ratio_array(np.asarray(data[f"wheel_speed_{w}_radps"]) * wheel_radius_m, speed)
        for w in WHEELS
    }
    derived["accel_lon_g"] = np.asarray(data["accel_lon_mps2"]) / G_MPS2
    derived["accel_lat_g"] = np.asarray(data["accel_lat_mps2"]) / G_MPS2
    derived["centripetal_g"] = np.asarray(data["yaw_rate_radps"]) * speed / G_MPS2
    derived["road_wheel_angle_rad"] = np.asarray(data["steering_wheel_angle_rad"]) / steering_ratio
    derived["speed_mps"] = speed
    derived["abs_active"] = np.asarray(data["abs_active"], dtype=np.float64)
    return np.column_stack([derived[c] for c in feature_columns(feature_set)]).astype(np.float32)


def slip_ratio_array(wheel_speed_mps, hub_speed_mps):
    """Eq. 6 over arrays, as roadgrip.vehicle.dynamics.slip_ratio does for one wheel in the compiled simulator."""
    den = np.maximum(np.maximum(np.abs(wheel_speed_mps), np.abs(hub_speed_mps)), SLIP_SPEED_FLOOR_MPS)
    return (wheel_speed_mps - hub_speed_mps) / den


def segment_ids(*keys: np.ndarray) -> np.ndarray:
    """An int id per sample that changes whenever any key changes from one sample to the next (samples in stream order)."""
    n = len(keys[0])
    change = np.zeros(n, dtype=bool)
    change[0] = True
    for key in keys:
        key = np.asarray(key)
        change[1:] |= key[1:] != key[:-1]
    return np.cumsum(change) - 1


def window_ends(segments: np.ndarray, length: int) -> np.ndarray:
    """Indices of the last sample of every window of `length` samples that lies inside one segment."""
    if length < 1:
        raise ValueError(f"window length must be >= 1, got {length!r}")
    segments = np.asarray(segments)
    ends = np.arange(length - 1, len(segments))
    return ends[segments[ends] == segments[ends - length + 1]]


def make_windows(features: np.ndarray, segments: np.ndarray, length: int) -> tuple[np.ndarray, np.ndarray]:
    """(windows (m, length, n_features), index of each window's last sample (m,))."""
    ends = window_ends(segments, length)
    offsets = np.arange(-length + 1, 1)
    return features[ends[:, None] + offsets[None, :]], ends


class Scaler:
    """Per-feature standardisation; fitted on training data only and saved with the model."""

    def __init__(self, mean=None, scale=None):
        self.mean_ = None if mean is None else np.asarray(mean, dtype=np.float32)
        self.scale_ = None if scale is None else np.asarray(scale, dtype=np.float32)

    def fit(self, windows: np.ndarray) -> Scaler:
        flat = windows.reshape(-1, windows.shape[-1])
        self.mean_ = flat.mean(axis=0).astype(np.float32)
        self.scale_ = np.maximum(flat.std(axis=0), 1e-6).astype(np.float32)
        return self

    def transform(self, windows: np.ndarray) -> np.ndarray:
        if self.mean_ is None:
            raise ValueError("Scaler is not fitted: call fit() on training windows first")
        return ((windows - self.mean_) / self.scale_).astype(np.float32)
