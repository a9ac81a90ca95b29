"""The generalization benchmark (CONTRACTS 4): can an estimator judge roads and cars it has never seen?

- Train: runs of the `random` preset on the midsize sedan and the paper's SUV (randomized around them), with mu drawn
  from bands that leave out [0.45, 0.55] and [0.85, 1.0] (roadgrip/sim/presets.py: generalization_scenarios).
- Calibrate the 90 % intervals: other runs of the same distribution (held out from training).
- Test: runs on the held-out compact hatchback (randomized around it), with mu drawn from the held-out bands only: mu
  values and a vehicle that training never saw. Steps only (ramps would cross the held-out bands).
For every estimator: RMSE and MAE over the excited samples (CONTRACTS 4: true friction utilization >= 0.5, or ABS) and over all
samples, coverage and width of the 90 % interval, and the share of samples the estimator judged excited.
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pyarrow as pa

from roadgrip.estimators.calibration import interval, utilization_bin
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.evaluation.physics import PHYSICS_ROWS, physics_on_runs
from roadgrip.models.q_learning import DEFAULT_ALLOWED_RANGE, QConfig, clip, refine_model
from roadgrip.models.registry import DISPLAY_NAMES, PAPER_MODELS
from roadgrip.sim.presets import generalization_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.training.fit import PreparedData, block_split, calibration_of, fit, prepare, subset
from roadgrip.training.pool import training_pool
from roadgrip.training.trainer import TrainConfig, predict

WINDOW_STRIDE = 2  # every other training window: neighbours are nearly identical, and 2 cores are few
TRAIN_CONFIG = TrainConfig(batch_size=256, max_epochs=60, patience=10)


def _train_and_test(args) -> list[dict]:
    """The model trained, calibrated on the calibration runs and run on the test windows; for SA-CNN-LSTM also its
    Q-learning refinement (on the training runs' validation blocks, then recalibrated) and its clipped predictions."""
    name, feature_set, train, calibration, test, seed = args
    start = time.perf_counter()
    train_idx, val_idx = block_split(train)
    fitted = fit(name, train, train_idx, val_idx, {}, replace(TRAIN_CONFIG, seed=seed))
    fitted.interval = calibration_of(fitted, calibration)
    x_test = fitted.scaler.transform(test.windows)
    pred = predict(fitted.model, x_test).astype(np.float64)
    rows = [
        {
            "model": DISPLAY_NAMES[name],
            "feature_set": feature_set,
            "pred": pred,
            "interval": fitted.interval,
            "fitted": fitted,
            "seconds": time.perf_counter() - start,
        }
    ]
    if name == "sa-cnn-lstm":
        rows.append(
            rows[0] | {"model": "SA-CNN-LSTM (clipped)", "pred": clip(pred, DEFAULT_ALLOWED_RANGE), "fitted": None}
        )
        refined = copy.deepcopy(fitted)
        x_val = refined.scaler.transform(train.windows[val_idx])
        refine_model(refined.model, x_val, train.targets[val_idx], QConfig(seed=seed))
        refined.interval = calibration_of(refined, calibration)
        rows.append(
            {
                "model": "SA-CNN-LSTM-Q",
                "feature_set": feature_set,
                "interval": refined.interval,
                "pred": predict(refined.model, x_test).astype(np.float64),
                "fitted": refined,
                "seconds": time.perf_counter() - start,
            }
        )
    return rows


def evaluate_predictions(model: str, feature_set: str, test: PreparedData, pred, lower, upper) -> dict:
    """The benchmark's row for one estimator's predictions and intervals on the test windows."""
    exc = test.excited
    m = test.measured
    judged = utilization_bin(m[:, 0], m[:, 1], m[:, 2] > 0.5, pred) == 2
    inside = (test.targets >= lower) & (test.targets <= upper)
    width = upper - lower
    inner = exc & (test.targets < 0.7)  # the held-out band inside the trained range: interpolation
    upper_band = exc & (test.targets >= 0.7)  # the band above it: extrapolation
    return {
        "model": model,
        "feature_set": feature_set,
        "rmse_excited": rmse(pred[exc], test.targets[exc]),
        "mae_excited": mae(pred[exc], test.targets[exc]),
        "rmse_excited_045_055": rmse(pred[inner], test.targets[inner]) if inner.any() else float("nan"),
        "rmse_excited_085_100": rmse(pred[upper_band], test.targets[upper_band]) if upper_band.any() else float("nan"),
        "rmse_all": rmse(pred, test.targets),
        "mae_all": mae(pred, test.targets),
        "coverage_all": float(inside.mean()),
        "coverage_excited": float(inside[exc].mean()),
        "coverage_not_excited": float(inside[~exc].mean()),
        "width_excited": float(width[exc].mean()),
        "width_not_excited": float(width[~exc].mean()),
        "judged_excited": float(judged.mean()),
        "truly_excited": float(exc.mean()),
        "out_of_range": int(((pred < DEFAULT_ALLOWED_RANGE[0]) | (pred > DEFAULT_ALLOWED_RANGE[1])).sum()),
        "n": len(pred),
        "n_excited": int(exc.sum()),
    }


def run_generalization_benchmark(
    seed: int = 0,
    models=PAPER_MODELS + ("sa-cnn-lstm-bounded",),
    feature_sets=("physics", "terminal"),
    workers: int = 2,
    progress: Callable[[str], None] | None = None,
):
    """(metrics rows, test predictions table, fitted models by (model, feature set), test data by feature set)."""
    say = progress or (lambda message: None)
    train_s, calib_s, test_s = (generalization_scenarios(part, seed) for part in ("train", "calibration", "test"))
    say(f"simulating {len(train_s) + len(calib_s) + len(test_s)} runs")
    tables = [simulate(s) for s in (train_s, calib_s, test_s)]
    vehicles = {s.vehicle.name: s.vehicle for s in train_s + calib_s + test_s}
    jobs, tests = [], {}
    for fs in feature_sets:
        train, calibration, test = (prepare(t, fs, vehicles=vehicles) for t in tables)
        train = subset(train, np.arange(0, len(train.targets), WINDOW_STRIDE))
        tests[fs] = test
        jobs += [(name, fs, train, calibration, test, seed) for name in models]
    say(f"training {len(jobs)} models")
    with training_pool(workers) as pool:
        results = [row for rows in pool.map(_train_and_test, jobs) for row in rows]
    metrics, predictions, fitted = [], [], {}
    for r in results:
        test = tests[r["feature_set"]]
        bins = utilization_bin(test.measured[:, 0], test.measured[:, 1], test.measured[:, 2] > 0.5, r["pred"])
        lower, upper = interval(r["pred"], bins, r["interval"])
        metrics.append(
            evaluate_predictions(r["model"], r["feature_set"], test, r["pred"], lower, upper)
            | {"train_seconds": r["seconds"]}
        )
        if r["fitted"] is not None:
            fitted[(r["model"], r["feature_set"])] = r["fitted"]
        predictions.append(_prediction_table(r["model"], r["feature_set"], test, r["pred"], lower, upper))
    test_table, test_vehicles = tables[2], {s.run_id: s.vehicle for s in test_s}
    for name, display in PHYSICS_ROWS.items():
        say(f"filtering the test runs with the {display}")
        test = tests[feature_sets[0]]
        pred, lower, upper = physics_on_runs(name, test_table, test_vehicles, test)
        metrics.append(evaluate_predictions(display, "-", test, pred, lower, upper))
        predictions.append(_prediction_table(display, "-", test, pred, lower, upper))
    return metrics, pa.concat_tables(predictions), fitted, tests


def _prediction_table(model, feature_set, test: PreparedData, pred, lower, upper) -> pa.Table:
    n = len(test.targets)
    return pa.table(
        {
            "model": [model] * n,
            "feature_set": [feature_set] * n,
            "run_id": test.runs.tolist(),
            "t_s": test.t_s,
            "mu_true": test.targets.astype(np.float64),
            "mu_pred": pred,
            "mu_lower": lower,
            "mu_upper": upper,
            "excited": test.excited,
        }
    )
