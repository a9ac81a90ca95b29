"""Splits for model selection that never put one group (a run, or a block of a run) on both sides."""

from __future__ import annotations

import numpy as np
from sklearn.model_selection import GroupKFold


def grouped_folds(groups: np.ndarray, n_folds: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """K folds over samples (or windows) labelled by group: no group is ever in both a fold's training and validation."""
    groups = np.asarray(groups)
    n_groups = len(np.unique(groups))
    if n_folds < 2 or n_folds > n_groups:
        raise ValueError(f"n_folds must be in [2, number of groups = {n_groups}], got {n_folds!r}")
    return [(train, val) for train, val in GroupKFold(n_splits=n_folds).split(np.zeros(len(groups)), groups=groups)]


def time_blocks(t_s: np.ndarray, block_s: float) -> np.ndarray:
    """Index of the block of `block_s` seconds that each sample falls in, counted from t = 0 of its run.

    With only a couple of runs per case (the paper's protocol), the 4:1 split for validation is made by interleaved blocks
    of time inside each run; windows are cut per (run, block), so that no window straddles training and validation."""
    if not block_s > 0:
        raise ValueError(f"block_s must be > 0, got {block_s!r}")
    return np.floor(np.asarray(t_s) / block_s + 1e-9).astype(np.int64)
