"""From a dataset table to a trained model: windows, the 4:1 split by interleaved time blocks, the scaler, the trainer,
and the calibration of the 90 % interval on the validation windows."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pyarrow as pa
import torch

from roadgrip.estimators.calibration import calibrate, utilization_bin
from roadgrip.estimators.excitation import excited
from roadgrip.features.folds import grouped_folds, time_blocks
from roadgrip.features.windows import (
    Scaler,
    feature_matrix,
    make_windows,
    needs_vehicle,
    segment_ids,
    vehicle_profile,
)
from roadgrip.models.registry import build_model, model_config
from roadgrip.training.trainer import TrainConfig, Trainer, TrainResult, predict

WINDOW = 10  # samples: 1 s of telemetry at 10 Hz
BLOCK_S = 4.0  # runs are cut in blocks of 4 s; windows never straddle blocks
N_FOLDS = 5  # block k of every 5 is validation in fold k: the paper's 4:1 split
SELECTION_FOLD = N_FOLDS - 1


@dataclass
class PreparedData:
    windows: np.ndarray  # (m, WINDOW, n_features), raw units
    targets: np.ndarray  # (m,) mu at each window's last sample
    runs: np.ndarray  # (m,) run id of each window
    blocks: np.ndarray  # (m,) time block of each window within its run
    t_s: np.ndarray  # (m,) time of each window's last sample
    feature_set: str
    excited: np.ndarray  # (m,) CONTRACTS 4 excitation of each window's last sample (true accelerations against true mu)
    measured: np.ndarray  # (m, 3) measured accel_lon, accel_lat and abs_active at each window's last sample


def prepare(table: pa.Table, feature_set: str, window: int = WINDOW, vehicles: dict | None = None) -> PreparedData:
    """Windows of a simulation dataset, cut per (run, 4 s block), labelled with the true mu.

    `vehicles` maps the dataset's `vehicle` column to VehicleParams, for feature sets that use the profile."""
    profile = None
    runs = np.asarray(table["run_id"].to_pylist())
    if needs_vehicle(feature_set):
        if vehicles is None:
            raise ValueError(f"feature set {feature_set!r} needs the vehicles of the dataset (its manifest)")
        names = table["vehicle"].to_pylist()
        profiles = {n: vehicle_profile(vehicles[n]) for n in set(names)}
        profile = {f: np.array([profiles[n][f] for n in names]) for f in next(iter(profiles.values()))}
    # one stream per run: features that difference consecutive samples see each run as a terminal streams it
    features = feature_matrix(table, feature_set, profile=profile, segments=segment_ids(runs))
    t_s = table["t_s"].to_numpy()
    blocks = time_blocks(t_s, BLOCK_S)
    windows, ends = make_windows(features, segment_ids(runs, blocks), window)
    mu = table["mu"].to_numpy()
    exc = excited(
        table["ax_true_mps2"].to_numpy(), table["ay_true_mps2"].to_numpy(), table["abs_active"].to_numpy(), mu
    )
    measured = np.column_stack(
        [
            table[c].to_numpy(zero_copy_only=False).astype(np.float64)
            for c in ("accel_lon_mps2", "accel_lat_mps2", "abs_active")
        ]
    )
    return PreparedData(
        windows,
        mu.astype(np.float32)[ends],
        runs[ends],
        blocks[ends],
        t_s[ends],
        feature_set,
        exc[ends],
        measured[ends],
    )


def subset(data: PreparedData, idx: np.ndarray) -> PreparedData:
    """The windows idx of a prepared data set."""
    return replace(
        data,
        windows=data.windows[idx],
        targets=data.targets[idx],
        runs=data.runs[idx],
        blocks=data.blocks[idx],
        t_s=data.t_s[idx],
        excited=data.excited[idx],
        measured=data.measured[idx],
    )


def block_split(data: PreparedData, fold: int = SELECTION_FOLD) -> tuple[np.ndarray, np.ndarray]:
    """(train, validation) window indices: validation is every block b with b % N_FOLDS == fold, in every run."""
    groups = data.blocks % N_FOLDS
    val = groups == fold
    return np.flatnonzero(~val), np.flatnonzero(val)


def run_folds(data: PreparedData, n_folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """K folds grouped by run: a run is never on both sides."""
    return grouped_folds(data.runs, n_folds)


@dataclass
class FittedModel:
    model_name: str
    config: object
    model: object
    scaler: Scaler
    result: TrainResult
    interval: dict  # conformal calibration by utilization bin (roadgrip/estimators/calibration.py)


def fit(
    model_name: str,
    data: PreparedData,
    train_idx: np.ndarray,
    val_idx: np.ndarray,
    overrides: dict | None = None,
    train_config: TrainConfig = TrainConfig(),
) -> FittedModel:
    scaler = Scaler().fit(data.windows[train_idx])
    x = scaler.transform(data.windows)
    config = model_config(model_name, data.windows.shape[2], data.windows.shape[1], **(overrides or {}))
    torch.manual_seed(train_config.seed)  # the initial weights, too, come from the seed
    model = build_model(model_name, config)
    result = Trainer(train_config).fit(model, x[train_idx], data.targets[train_idx], x[val_idx], data.targets[val_idx])
    fitted = FittedModel(model_name, config, model, scaler, result, {})
    fitted.interval = calibration_of(fitted, data, val_idx)
    return fitted


def calibration_of(fitted: FittedModel, data: PreparedData, idx: np.ndarray | None = None) -> dict:
    """Conformal interval calibration of a fitted model on windows of `data` (all of them, or `idx`): held-out runs
    are the honest choice; the validation blocks of the training runs are the fallback that `fit` uses."""
    idx = np.arange(len(data.targets)) if idx is None else idx
    pred = predict(fitted.model, fitted.scaler.transform(data.windows[idx]))
    m = data.measured[idx]
    bins = utilization_bin(m[:, 0], m[:, 1], m[:, 2] > 0.5, pred)
    return calibrate(pred, data.targets[idx], bins) | {"calibrated_on": len(idx)}


def cross_validate(
    model_name: str,
    data: PreparedData,
    n_folds: int,
    overrides: dict | None = None,
    train_config: TrainConfig = TrainConfig(),
) -> list[float]:
    """Validation RMSE of each of K folds grouped by run (each fold's model early-stops on its own validation runs)."""
    return [
        fit(model_name, data, tr, va, overrides, train_config).result.best_val_rmse
        for tr, va in run_folds(data, n_folds)
    ]


def save_fitted(path, fitted: FittedModel, feature_set: str, training: dict):
    """Checkpoint with everything the estimator needs (roadgrip/estimators/learned.py reads it)."""
    from roadgrip.features.windows import feature_columns
    from roadgrip.training.checkpoint import save_checkpoint

    meta = {
        "estimator_name": fitted.model_name,
        "feature_set": feature_set,
        "features": list(feature_columns(feature_set)),
        "window": fitted.config.window,
        "scaler_mean": fitted.scaler.mean_,
        "scaler_scale": fitted.scaler.scale_,
        "interval": fitted.interval,
        "training": {
            "best_val_rmse": fitted.result.best_val_rmse,
            "best_epoch": fitted.result.best_epoch,
            "epochs_run": fitted.result.epochs_run,
            **training,
        },
    }
    return save_checkpoint(path, fitted.model_name, fitted.config, fitted.model, meta)
