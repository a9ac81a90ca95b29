"""The generalization benchmark (DESIGN 4): can an estimator judge roads and cars it has never seen?

- Train: runs of the `random` preset on the midsize sedan and the paper's SUV (randomized around them), with mu drawn
  from TRAIN_MU_BANDS only.
- Calibrate the 90 % intervals: other runs of the same distribution (held out from training).
- Test: runs on the held-out compact hatchback (randomized around it), with mu drawn from TEST_MU_BANDS only: mu values
  and a vehicle that training never saw. Steps only (ramps would cross the held-out bands).
For every estimator: RMSE and MAE over the excited samples (DESIGN 4: true friction utilization >= 0.5, or ABS) and over all
samples, coverage and width of the 90 % interval, and the share of samples the estimator judged excited.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
import pyarrow as pa

from roadgrip.estimators.calibration import interval, utilization_bin
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.models.registry import DISPLAY_NAMES, MODELS
from roadgrip.sim.presets import TRAINING_VEHICLES, random_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.training.fit import PreparedData, block_split, calibration_of, fit, prepare
from roadgrip.training.trainer import TrainConfig, predict
from roadgrip.vehicle.params import COMPACT_HATCHBACK

TRAIN_MU_BANDS = ((0.1, 0.45), (0.55, 0.85))
TEST_MU_BANDS = ((0.45, 0.55), (0.85, 1.0))
TRAIN_RUNS, CALIBRATION_RUNS, TEST_RUNS = 160, 40, 40
WINDOW_STRIDE = 2  # every other training window: neighbours are nearly identical, and 2 cores are few
TRAIN_CONFIG = TrainConfig(batch_size=256, max_epochs=60, patience=10)


def generalization_scenarios(seed: int = 0):
    common = {"ramps": False}
    train = random_scenarios(TRAIN_RUNS, seed, mu_bands=TRAIN_MU_BANDS, vehicles=TRAINING_VEHICLES, prefix="train",
                             **common)
    calibration = random_scenarios(CALIBRATION_RUNS, seed + 1, mu_bands=TRAIN_MU_BANDS, vehicles=TRAINING_VEHICLES,
                                   prefix="calib", **common)
    test = random_scenarios(TEST_RUNS, seed + 2, mu_bands=TEST_MU_BANDS, vehicles=(COMPACT_HATCHBACK,), prefix="test",
                            **common)
    return train, calibration, test


def subset(data: PreparedData, idx: np.ndarray) -> PreparedData:
    return replace(data, windows=data.windows[idx], targets=data.targets[idx], runs=data.runs[idx],
                   blocks=data.blocks[idx], t_s=data.t_s[idx], excited=data.excited[idx], measured=data.measured[idx])


def _worker_init():
    import torch

    torch.set_num_threads(1)


def _train_and_test(args) -> dict:
    name, feature_set, train, calibration, test, seed = args
    start = time.perf_counter()
    fitted = fit(name, train, *block_split(train), {}, replace(TRAIN_CONFIG, seed=seed))
    fitted.interval = calibration_of(fitted, calibration)
    pred = predict(fitted.model, fitted.scaler.transform(test.windows)).astype(np.float64)
    return {"model": DISPLAY_NAMES[name], "feature_set": feature_set, "pred": pred, "fitted": fitted,
            "seconds": time.perf_counter() - start}


def evaluate_predictions(model: str, feature_set: str, test: PreparedData, pred, lower, upper) -> dict:
    """The benchmark's row for one estimator's predictions and intervals on the test windows."""
    exc = test.excited
    m = test.measured
    judged = utilization_bin(m[:, 0], m[:, 1], m[:, 2] > 0.5, pred) == 2
    inside = (test.targets >= lower) & (test.targets <= upper)
    width = upper - lower
    return {
        "model": model, "feature_set": feature_set,
        "rmse_excited": rmse(pred[exc], test.targets[exc]), "mae_excited": mae(pred[exc], test.targets[exc]),
        "rmse_all": rmse(pred, test.targets), "mae_all": mae(pred, test.targets),
        "coverage_all": float(inside.mean()), "coverage_excited": float(inside[exc].mean()),
        "coverage_not_excited": float(inside[~exc].mean()),
        "width_excited": float(width[exc].mean()), "width_not_excited": float(width[~exc].mean()),
        "judged_excited": float(judged.mean()), "truly_excited": float(exc.mean()),
        "out_of_range": int(((pred < 0.0) | (pred > 1.2)).sum()), "n": int(len(pred)), "n_excited": int(exc.sum()),
    }


def run_generalization_benchmark(seed: int = 0, models=tuple(MODELS), feature_sets=("physics", "terminal"),
                                 workers: int = 2, progress: Callable[[str], None] | None = None):
    """(metrics rows, test predictions table, fitted models by (model, feature set), test data by feature set)."""
    say = progress or (lambda message: None)
    train_s, calib_s, test_s = generalization_scenarios(seed)
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
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        results = list(pool.map(_train_and_test, jobs))
    metrics, predictions, fitted = [], [], {}
    for r in results:
        test = tests[r["feature_set"]]
        bins = utilization_bin(test.measured[:, 0], test.measured[:, 1], test.measured[:, 2] > 0.5, r["pred"])
        lower, upper = interval(r["pred"], bins, r["fitted"].interval)
        metrics.append(evaluate_predictions(r["model"], r["feature_set"], test, r["pred"], lower, upper)
                       | {"train_seconds": r["seconds"]})
        fitted[(r["model"], r["feature_set"])] = r["fitted"]
        predictions.append(pa.table({
            "model": [r["model"]] * len(test.targets), "feature_set": [r["feature_set"]] * len(test.targets),
            "run_id": test.runs.tolist(), "t_s": test.t_s, "mu_true": test.targets.astype(np.float64),
            "mu_pred": r["pred"], "mu_lower": lower, "mu_upper": upper, "excited": test.excited}))
    return metrics, pa.concat_tables(predictions), fitted, tests
