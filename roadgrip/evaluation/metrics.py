"""Eq. 14: root mean square error and mean absolute error, in units of mu."""

import numpy as np


def rmse(pred, true) -> float:
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.size == 0:
        raise ValueError(f"rmse needs two non-empty arrays of one shape, got {pred.shape} and {true.shape}")
    return float(np.sqrt(np.mean((pred - true) ** 2)))


def mae(pred, true) -> float:
    pred, true = np.asarray(pred, dtype=np.float64), np.asarray(true, dtype=np.float64)
    if pred.shape != true.shape or pred.size == 0:
        raise ValueError(f"mae needs two non-empty arrays of one shape, got {pred.shape} and {true.shape}")
    return float(np.mean(np.abs(pred - true)))
