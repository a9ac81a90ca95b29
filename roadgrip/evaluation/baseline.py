"""The prior-only baseline every estimator table prints beside the estimators, and the skill score against it.

The baseline knows nothing of the drive: it answers pmf's prior (roadgrip/estimators/pmf.py PRIOR over MU_GRID) on every
sample, its median as the estimate and its 5 % and 95 % quantiles as the 90 % interval, read by pmf's own quantile rule
(pmf.mu_quantile), so that the baseline is exactly what pmf answers from its prior. An estimator that does not beat
it in a cell has learned nothing there from the signals. Skill of an estimator in a cell: 1 - RMSE_est / RMSE_prior, both
over the estimator's samples of that cell (1: perfect, 0: no better than the prior, below 0: worse).
"""

from __future__ import annotations

from dataclasses import dataclass

from roadgrip.estimators.pmf import PRIOR, mu_quantile

PRIOR_NAME = "prior"  # the baseline's name in the tables


@dataclass(frozen=True)
class PriorBaseline:
    """A constant estimate: mu_median and the interval [mu_lower, mu_upper]."""

    mu_median: float
    mu_lower: float
    mu_upper: float


def prior_baseline() -> PriorBaseline:
    """pmf's prior as a constant estimate: median and 90 % interval (0.780 in [0.189, 1.077] for today's prior)."""
    return PriorBaseline(*(mu_quantile(PRIOR, q) for q in (0.5, 0.05, 0.95)))


def skill(rmse_estimator: float, rmse_prior: float) -> float:
    """1 - rmse_estimator / rmse_prior (NaN where the prior is exact: nothing to beat)."""
    return 1.0 - rmse_estimator / rmse_prior if rmse_prior > 0.0 else float("nan")
