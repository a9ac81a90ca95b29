"""The prior-only baseline every estimator table prints beside the estimators, and the skill score against it.

The baseline knows nothing of the drive: it answers pmf's prior (roadgrip/estimators/pmf.py PRIOR over MU_GRID) on every
sample, its median as the estimate and its 5 % and 95 % quantiles as the 90 % interval. An estimator that does not beat
it in a cell has learned nothing there from the signals. Skill of an estimator in a cell: 1 - RMSE_est / RMSE_prior, both
over the estimator's samples of that cell (1: perfect, 0: no better than the prior, below 0: worse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from roadgrip.estimators.pmf import MU_GRID, PRIOR

PRIOR_NAME = "prior"  # the baseline's name in the tables


@dataclass(frozen=True)
class PriorBaseline:
    """A constant estimate: mu_median and the interval [mu_lower, mu_upper]."""

    mu_median: float
    mu_lower: float
    mu_upper: float


def grid_quantile(grid, weights, q: float) -> float:
    """The smallest grid value whose cumulative weight reaches q (weights normalised here)."""
    if not 0.0 < q < 1.0:
        raise ValueError(f"grid_quantile: q must lie in (0, 1), got {q!r}")
    cdf = np.cumsum(weights) / np.sum(weights)
    return float(np.asarray(grid)[min(int(np.searchsorted(cdf, q - 1e-12)), len(cdf) - 1)])


def prior_baseline() -> PriorBaseline:
    """pmf's prior as a constant estimate: median and 90 % interval (0.775 in [0.20, 1.075] for today's prior)."""
    return PriorBaseline(*(grid_quantile(MU_GRID, PRIOR, q) for q in (0.5, 0.05, 0.95)))


def skill(rmse_estimator: float, rmse_prior: float) -> float:
    """1 - rmse_estimator / rmse_prior (NaN where the prior is exact: nothing to beat)."""
    return 1.0 - rmse_estimator / rmse_prior if rmse_prior > 0.0 else float("nan")
