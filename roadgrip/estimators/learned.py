"""A trained model (checkpoint) behind the estimator interface."""

from __future__ import annotations

import functools
from collections import deque
from importlib import resources
from pathlib import Path

import numpy as np
import pyarrow as pa

from roadgrip.estimators.base import Estimate, Estimator, estimate_table
from roadgrip.estimators.calibration import interval, utilization_bin
from roadgrip.estimators.excitation import excited
from roadgrip.features.windows import (
    Scaler,
    feature_matrix,
    features_from_columns,
    input_columns,
    make_windows,
    vehicle_profile,
)
from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

DEFAULT_MODEL = "default"


class LearnedEstimator(Estimator):
    """Estimates mu at the last sample of each window of `window` samples; the 90 % interval is conformal, calibrated
    by excitation level on data the model did not train on (roadgrip/estimators/calibration.py)."""

    def __init__(self, model, model_name: str, meta: dict):
        self.model = model
        self.model_name = model_name
        self.meta = meta
        self.name = meta.get("estimator_name", model_name)
        self.feature_set = meta["feature_set"]
        self.window = int(meta["window"])
        self.required, self.optional = input_columns(self.feature_set)
        self.scaler = Scaler(meta["scaler_mean"], meta["scaler_scale"])
        self.calibration = meta["interval"]

    # torch is imported where a model is loaded or run, not with this module: `load_estimator("ekf")` then costs no
    # torch (130 MB of RSS in each process of `roadgrip serve`, measured with roadgrip.cloud.process.rss_mb)
    @classmethod
    def load(cls, path: str | Path) -> LearnedEstimator:
        from roadgrip.training.checkpoint import load_checkpoint

        model, name, meta = load_checkpoint(path)
        return cls(model, name, meta)

    def _estimates(self, windows: np.ndarray, accel_lon, accel_lat, abs_active):
        from roadgrip.training.trainer import predict

        mu = predict(self.model, self.scaler.transform(windows)).astype(np.float64)
        lower, upper = interval(mu, utilization_bin(accel_lon, accel_lat, abs_active, mu), self.calibration)
        return mu, lower, upper, excited(accel_lon, accel_lat, abs_active, mu)

    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams = PAPER_SUV) -> pa.Table:
        features = feature_matrix(table, self.feature_set, profile=vehicle_profile(vehicle), segments=segments)
        windows, ends = make_windows(features, np.asarray(segments), self.window)
        col = {
            c: table[c].to_numpy(zero_copy_only=False)[ends] for c in ("accel_lon_mps2", "accel_lat_mps2", "abs_active")
        }
        mu, lower, upper, exc = self._estimates(
            windows, col["accel_lon_mps2"], col["accel_lat_mps2"], col["abs_active"]
        )
        return estimate_table(
            {
                "vehicle_id": np.asarray(table["vehicle_id"].to_pylist(), dtype=object)[ends],
                "timestamp_ms": table["timestamp_ms"].to_numpy()[ends],
                "mu": mu,
                "mu_lower": lower,
                "mu_upper": upper,
                "excited": exc,
                "estimator": [self.name] * len(ends),
            }
        )

    def start(self, vehicle: VehicleParams = PAPER_SUV):
        # previous: the last sample's inputs, for the features that difference consecutive samples
        return {"buffer": deque(maxlen=self.window), "profile": vehicle_profile(vehicle), "previous": None}

    def update(self, state, sample: dict) -> Estimate | None:
        inputs = {k: sample[k] for k in self.required}
        inputs |= {k: sample[k] for k in self.optional if sample.get(k) is not None}
        row = features_from_columns(
            {k: np.asarray([float(v)], dtype=np.float64) for k, v in inputs.items()},
            self.feature_set,
            profile=state["profile"],
            previous=state["previous"],
        )
        state["previous"] = {k: float(v) for k, v in inputs.items()}
        state["buffer"].append(row[0].tolist())
        if len(state["buffer"]) < self.window:
            return None
        windows = np.asarray([state["buffer"]], dtype=np.float32)
        mu, lower, upper, exc = self._estimates(
            windows, sample["accel_lon_mps2"], sample["accel_lat_mps2"], bool(sample["abs_active"])
        )
        return Estimate(
            str(sample["vehicle_id"]),
            int(sample["timestamp_ms"]),
            float(mu[0]),
            float(lower[0]),
            float(upper[0]),
            bool(exc[0]),
            self.name,
        )

    def reset(self, state) -> None:
        state["buffer"].clear()
        state["previous"] = None

    def state_to_dict(self, state) -> dict:
        return {
            "buffer": [list(row) for row in state["buffer"]],
            "profile": dict(state["profile"]),
            "previous": state["previous"],
        }

    def state_from_dict(self, data: dict):
        # states saved before the profile was kept whole held only the wheel radius and steering ratio
        profile = data.get("profile") or {
            "wheel_radius_m": data["wheel_radius_m"],
            "steering_ratio": data["steering_ratio"],
        }
        return {
            "buffer": deque((list(row) for row in data["buffer"]), maxlen=self.window),
            "profile": profile,
            "previous": data.get("previous"),
        }


def default_model_path() -> Path:
    return Path(str(resources.files("roadgrip.estimators").joinpath("default_model.pt")))


def load_estimator(spec: str | Path = DEFAULT_MODEL) -> Estimator:
    """An estimator from a model file, or by name: 'default' is the model shipped in the package, 'pmf' the Bayesian
    grid filter (roadgrip/estimators/pmf.py), 'ekf' and 'ukf' the Kalman filters (roadgrip/estimators/physics.py).
    Every estimator comes with the physics guard on its output (roadgrip/estimators/guard.py)."""
    from roadgrip.estimators.guard import GuardedEstimator

    return GuardedEstimator(_unguarded_estimator(spec))


def _named_estimators() -> dict:
    """The one list of the estimators the project ships by name: name -> a factory of the unguarded estimator. An
    estimator added here is one `load_estimator` takes, and one tests/estimators/test_contract.py checks."""
    from roadgrip.estimators.physics import PHYSICS_ESTIMATORS, physics_estimator
    from roadgrip.estimators.pmf import PMFEstimator

    return {
        DEFAULT_MODEL: lambda: LearnedEstimator.load(default_model_path()),
        PMFEstimator.name: PMFEstimator,
        **{name: functools.partial(physics_estimator, name) for name in PHYSICS_ESTIMATORS},
    }


def estimator_names() -> tuple[str, ...]:
    """The names `load_estimator` takes besides model files: every estimator the project ships."""
    return tuple(_named_estimators())


def _unguarded_estimator(spec: str | Path) -> Estimator:
    named = _named_estimators()
    if str(spec) in named:
        return named[str(spec)]()
    path = Path(spec)
    if path.suffix == ".pt" or path.exists():
        return LearnedEstimator.load(path)
    raise ValueError(f"--model must be a model file (.pt) or one of {list(named)}, got {str(spec)!r}")
