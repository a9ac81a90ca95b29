"""Feature sets and windows of consecutive samples.

A window is `length` consecutive samples of one segment (a run, or a stretch of one vehicle's stream without a gap); its
label is the value at its last sample, so a model that reads a window estimates mu now from the recent past, as it must in
a live stream. Windows never cross segments: a window whose first and last samples lie in different segments is dropped.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa

from roadgrip.data.schema import WHEELS
from roadgrip.validation import check_choice

WHEEL_SPEEDS = tuple(f"wheel_speed_{w}_radps" for w in WHEELS)
FEATURE_SETS = {
    # paper 3.3: yaw rate, longitudinal speed, lateral speed and the four wheel angular speeds
    "paper": ("yaw_rate_radps", "speed_mps", "lateral_speed_mps") + WHEEL_SPEEDS,
    # what a production terminal sends (DESIGN 3.1), without the lateral speed that only test vehicles measure
    "terminal": ("speed_mps", "accel_lon_mps2", "accel_lat_mps2", "yaw_rate_radps", "steering_wheel_angle_rad")
    + WHEEL_SPEEDS,
}


def feature_columns(feature_set: str) -> tuple[str, ...]:
    check_choice("features", "feature_set", feature_set, set(FEATURE_SETS))
    return FEATURE_SETS[feature_set]


def feature_matrix(table: pa.Table, feature_set: str) -> np.ndarray:
    """(n_samples, n_features) float32 matrix of a feature set's columns; a missing column is an error naming it."""
    columns = feature_columns(feature_set)
    missing = [c for c in columns if c not in table.column_names]
    if missing:
        raise ValueError(f"feature set {feature_set!r} needs column(s) {missing}, which the data lacks")
    return np.column_stack([table[c].to_numpy(zero_copy_only=False).astype(np.float32) for c in columns])


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
