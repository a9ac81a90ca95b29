"""The paper benchmark (paper 5.1, DESIGN 4): Tables 2-6 and Figures 4-8 regenerated.

Protocol, for each feature set:
- per condition, as the paper: train on the condition's first experiment (straight and circular runs), with the 4:1 split
  for model selection made by interleaved 4 s blocks of time (every fifth block validates); test on the second experiment;
- also one model per architecture trained on all five conditions' first experiments, tested on each condition's second;
- every architecture gets the same search budget: SEARCH_BUDGET configs, the one with the lowest validation RMSE is kept;
- reference row "Constant (training mean)": what a model that ignores its input scores, to show what the numbers mean.
RMSE and MAE (eq. 14) over every test window (all samples with a full 1 s window behind them).
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.models.registry import DISPLAY_NAMES, MODELS, SEARCH_SPACES
from roadgrip.sim.presets import PAPER_CONDITIONS
from roadgrip.training.fit import PreparedData, block_split, fit, prepare
from roadgrip.training.trainer import TrainConfig, predict

FEATURE_SETS = ("paper", "terminal")
SCOPES = tuple(PAPER_CONDITIONS) + ("all",)
CONSTANT = "Constant (training mean)"


@dataclass
class Job:
    scope: str
    feature_set: str
    model_name: str
    candidate: int
    overrides: dict
    train: PreparedData
    test_windows: np.ndarray
    seed: int


def _worker_init():
    import torch

    torch.set_num_threads(1)


def _run_job(job: Job) -> dict:
    start = time.perf_counter()
    train_idx, val_idx = block_split(job.train)
    fitted = fit(job.model_name, job.train, train_idx, val_idx, job.overrides, TrainConfig(seed=job.seed))
    return {
        "scope": job.scope, "feature_set": job.feature_set, "model_name": job.model_name, "candidate": job.candidate,
        "overrides": job.overrides, "val_rmse": fitted.result.best_val_rmse, "best_epoch": fitted.result.best_epoch,
        "test_pred": predict(fitted.model, fitted.scaler.transform(job.test_windows)),
        "seconds": time.perf_counter() - start,
    }


def _split(table: pa.Table, experiment: int, condition: str | None) -> pa.Table:
    mask = pc.equal(table["experiment"], experiment)
    if condition is not None:
        mask = pc.and_(mask, pc.equal(table["condition"], condition))
    return table.filter(mask)


def run_paper_benchmark(table: pa.Table, models=tuple(MODELS), feature_sets=FEATURE_SETS, seed: int = 0,
                        workers: int = 2, progress: Callable[[int, int], None] | None = None) -> tuple[list, pa.Table]:
    """(metrics rows, predictions table) of the paper protocol over a `paper` preset dataset."""
    tests = {(fs, c): prepare(_split(table, 2, c), fs) for fs in feature_sets for c in PAPER_CONDITIONS}
    jobs = []
    for fs in feature_sets:
        for scope in SCOPES:
            train = prepare(_split(table, 1, None if scope == "all" else scope), fs)
            conditions = list(PAPER_CONDITIONS) if scope == "all" else [scope]
            test_windows = np.concatenate([tests[(fs, c)].windows for c in conditions])
            for name in models:
                for k, overrides in enumerate(SEARCH_SPACES[name]):
                    jobs.append(Job(scope, fs, name, k, overrides, train, test_windows, seed))
    results = []
    ctx = multiprocessing.get_context("spawn")
    with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        futures = [pool.submit(_run_job, job) for job in jobs]
        for done, future in enumerate(cf.as_completed(futures), 1):
            results.append(future.result())
            if progress is not None:
                progress(done, len(jobs))
    best = {}
    for r in results:
        key = (r["scope"], r["feature_set"], r["model_name"])
        if key not in best or r["val_rmse"] < best[key]["val_rmse"]:
            best[key] = r
    metrics, predictions = [], []
    for (scope, fs, name), r in sorted(best.items()):
        conditions = list(PAPER_CONDITIONS) if scope == "all" else [scope]
        offset = 0
        for c in conditions:
            test = tests[(fs, c)]
            pred = r["test_pred"][offset : offset + len(test.targets)]
            offset += len(test.targets)
            metrics.append(_row(c, DISPLAY_NAMES[name], fs, scope, pred, test,
                                {"val_rmse": r["val_rmse"], "config": r["overrides"], "best_epoch": r["best_epoch"]}))
            predictions.append(_predictions(c, DISPLAY_NAMES[name], fs, scope, test, pred))
    for fs in feature_sets:
        for scope in SCOPES:
            train_mu = _split(table, 1, None if scope == "all" else scope)["mu"].to_numpy()
            for c in ([scope] if scope != "all" else PAPER_CONDITIONS):
                test = tests[(fs, c)]
                pred = np.full(len(test.targets), train_mu.mean(), dtype=np.float32)
                metrics.append(_row(c, CONSTANT, fs, scope, pred, test, {}))
    return metrics, pa.concat_tables(predictions)


def _row(condition, model, feature_set, scope, pred, test: PreparedData, extra) -> dict:
    true, exc = test.targets, test.excited
    return {"condition": condition, "model": model, "feature_set": feature_set,
            "trained_on": "all" if scope == "all" else "condition", "rmse": rmse(pred, true), "mae": mae(pred, true),
            "n": int(len(true)), "rmse_excited": rmse(pred[exc], true[exc]) if exc.any() else float("nan"),
            "n_excited": int(exc.sum()), **extra}


def _predictions(condition, model, feature_set, scope, test: PreparedData, pred) -> pa.Table:
    n = len(pred)
    return pa.table({
        "condition": [condition] * n, "trained_on": ["all" if scope == "all" else "condition"] * n,
        "model": [model] * n, "feature_set": [feature_set] * n, "run_id": test.runs.tolist(),
        "road": ["circular" if "circular" in r else "straight" for r in test.runs.tolist()],
        "t_s": test.t_s, "mu_true": test.targets.astype(np.float64), "mu_pred": np.asarray(pred, dtype=np.float64),
    })
