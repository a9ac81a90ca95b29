"""Honest 90 % intervals: split-conformal calibration on held-out data, separately by excitation level (Mondrian).

Under steady driving a tire's force hardly depends on mu, so an estimate there is little more than a prior and its error
is large; while the tires work hard it is informative. One interval width for both would be too wide when excited and too
narrow when not. So each estimate is put in a bin by the friction utilization the estimator itself sees (measured
accelerations against its own mu estimate; ABS acting counts as the top bin), and each bin has its own residual quantiles,
taken on calibration data the model did not train on. Split conformal prediction (Vovk et al. 2005; Angelopoulos and
Bates 2021) then guarantees the coverage on data like the calibration data, per bin.
"""

from __future__ import annotations

import math

import numpy as np

from roadgrip.estimators.excitation import EXCITATION_UTILIZATION
from roadgrip.units import G_MPS2

UTILIZATION_EDGES = (
    0.25,
    EXCITATION_UTILIZATION,
)  # bins: < 0.25, 0.25-0.5, >= 0.5 or ABS (the last is CONTRACTS 4's "excited")
COVERAGE = 0.90


def utilization_bin(accel_lon_mps2, accel_lat_mps2, abs_active, mu_estimate) -> np.ndarray:
    """Excitation bin (0 .. len(UTILIZATION_EDGES)) of each estimate, from what the estimator can see."""
    utilization = np.hypot(accel_lon_mps2, accel_lat_mps2) / (np.maximum(mu_estimate, 0.05) * G_MPS2)
    bins = np.searchsorted(UTILIZATION_EDGES, utilization, side="right")
    return np.where(np.asarray(abs_active, dtype=bool), len(UTILIZATION_EDGES), bins)


def calibrate(predictions, truth, bins, coverage: float = COVERAGE) -> dict:
    """Per-bin conformal quantiles of the residual truth - prediction: the interval is [pred + q_low, pred + q_high]."""
    predictions, truth, bins = np.asarray(predictions), np.asarray(truth), np.asarray(bins)
    residual = truth - predictions
    alpha = 1.0 - coverage
    q_low, q_high, counts = [], [], []
    for b in range(len(UTILIZATION_EDGES) + 1):
        r = residual[bins == b]
        if r.size == 0:  # no calibration data in this bin: fall back on all of it
            r = residual
        n = r.size
        level_high = min(math.ceil((n + 1) * (1.0 - alpha / 2.0)) / n, 1.0)  # finite-sample correction
        level_low = max(math.floor((n + 1) * (alpha / 2.0)) / n, 0.0)
        q_low.append(float(np.quantile(r, level_low, method="lower")))
        q_high.append(float(np.quantile(r, level_high, method="higher")))
        counts.append(int((bins == b).sum()))
    return {
        "method": "split conformal by utilization bin",
        "coverage": coverage,
        "edges": list(UTILIZATION_EDGES),
        "q_low": q_low,
        "q_high": q_high,
        "counts": counts,
    }


def interval(predictions, bins, calibration: dict) -> tuple[np.ndarray, np.ndarray]:
    q_low = np.asarray(calibration["q_low"])[bins]
    q_high = np.asarray(calibration["q_high"])[bins]
    return predictions + q_low, predictions + q_high
