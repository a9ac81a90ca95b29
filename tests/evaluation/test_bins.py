"""roadgrip/evaluation/bins.py and baseline.py against inputs whose answers are worked out by hand."""

import math

import numpy as np
import pytest

from roadgrip.estimators.pmf import MU_GRID, PRIOR, mu_quantile
from roadgrip.evaluation.baseline import prior_baseline, skill
from roadgrip.evaluation.bins import ABS_BIN, binned_metrics, catalogue_profile, utilization_bin
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, TireParams


def test_utilization_bin_boundaries_belong_to_the_upper_bin():
    # mu 1: utilization = |a| / g; 0.3, 0.5 and 0.8 g open their bins, just below stays in the bin before
    ax = np.array([0.2999, 0.3, 0.4999, 0.5, 0.7999, 0.8, 2.0]) * G_MPS2
    names = utilization_bin(ax, np.zeros(7), np.ones(7), np.zeros(7, bool))
    assert names.tolist() == ["< 0.3", "0.3-0.5", "0.3-0.5", "0.5-0.8", "0.5-0.8", ">= 0.8", ">= 0.8"]


def test_utilization_bin_combines_both_axes_and_floors_mu_at_005():
    # 3 and 4 m/s^2 make 5 m/s^2: on mu 1 that is 5 / 9.807 = 0.51; mu 0.01 is read as 0.05: 0.02 g / 0.05 g = 0.4
    names = utilization_bin([3.0, 0.02 * G_MPS2], [4.0, 0.0], [1.0, 0.01], [False, False])
    assert names.tolist() == ["0.5-0.8", "0.3-0.5"]


def test_abs_overrides_any_utilization():
    names = utilization_bin([0.0, 0.9 * G_MPS2, 0.1 * G_MPS2], [0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [True, True, False])
    assert names.tolist() == [ABS_BIN, ABS_BIN, "< 0.3"]


def _hand_rows(baseline_mu=None):
    bins = np.array(["< 0.3", "< 0.3", ABS_BIN, ">= 0.8"], dtype=object)
    truth = [0.5, 0.5, 0.2, 1.0]
    mu = [0.6, 0.3, 0.2, 0.9]
    lower = [0.4, 0.1, 0.2, -0.1]
    upper = [0.7, 0.45, 0.2, 1.0]
    excited = [False, True, True, True]
    bound = [0.6, 0.0, 0.1, 0.95]
    rows = binned_metrics(mu, lower, upper, excited, truth, bins, bound, baseline_mu)
    return {r["bin"]: r for r in rows}


def test_binned_metrics_by_hand():
    rows = _hand_rows()
    low = rows["< 0.3"]
    assert low["n"] == 2
    assert low["rmse"] == pytest.approx(math.sqrt((0.1**2 + 0.2**2) / 2))
    assert low["mae"] == pytest.approx(0.15)
    assert low["coverage"] == 0.5  # 0.5 in [0.4, 0.7], not in [0.1, 0.45]
    assert low["width"] == pytest.approx((0.3 + 0.35) / 2)
    assert low["judged_excited"] == 0.5
    assert low["below_bound"] == 0.0  # 0.6 on a bound of 0.6 is not below it
    assert rows[ABS_BIN]["coverage"] == 1.0  # an interval's ends count as inside: 0.2 in [0.2, 0.2]
    assert rows[ABS_BIN]["rmse"] == 0.0
    high = rows[">= 0.8"]
    assert high["below_bound"] == 1.0  # 0.9 below the proven 0.95
    assert high["negative"] == 1  # a lower end of -0.1
    assert high["coverage"] == 1.0
    assert rows["0.3-0.5"] == {"bin": "0.3-0.5", "n": 0}
    assert rows["0.5-0.8"] == {"bin": "0.5-0.8", "n": 0}
    everything = rows["all"]
    assert everything["n"] == 4
    assert everything["coverage"] == 0.75
    assert everything["below_bound"] == 0.25
    assert everything["negative"] == 1
    assert "skill" not in everything


def test_binned_metrics_skill_against_a_constant_over_the_same_samples():
    rows = _hand_rows(baseline_mu=0.775)
    low = rows["< 0.3"]
    assert low["prior_rmse"] == pytest.approx(0.275)  # both truths are 0.5
    assert low["skill"] == pytest.approx(1.0 - math.sqrt(0.025) / 0.275)
    assert rows[ABS_BIN]["skill"] == pytest.approx(1.0)  # exact where the prior misses by 0.575
    everything = rows["all"]
    prior = math.sqrt((0.275**2 * 2 + 0.575**2 + 0.225**2) / 4)
    assert everything["prior_rmse"] == pytest.approx(prior)
    assert everything["skill"] == pytest.approx(1.0 - math.sqrt((0.01 + 0.04 + 0.0 + 0.01) / 4) / prior)


def test_skill_is_nan_where_the_prior_is_exact():
    assert math.isnan(skill(0.1, 0.0))
    assert skill(0.1, 0.2) == pytest.approx(0.5)
    assert skill(0.3, 0.2) == pytest.approx(-0.5)


def test_mu_quantile_by_hand():
    """pmf's quantile rule, which the baseline reads the prior by: each grid cell a bin of one step around its value,
    linear within it."""
    step = MU_GRID[1] - MU_GRID[0]
    pm = np.zeros(MU_GRID.size)
    pm[10], pm[30] = 0.5, 0.5  # half the mass in the bin around MU_GRID[10], half around MU_GRID[30]
    assert mu_quantile(pm, 0.25) == pytest.approx(MU_GRID[10])
    assert mu_quantile(pm, 0.05) == pytest.approx(MU_GRID[10] - 0.4 * step)
    assert mu_quantile(pm, 0.95) == pytest.approx(MU_GRID[30] + 0.4 * step)
    with pytest.raises(ValueError, match="level must lie in"):
        mu_quantile(pm, 1.0)
    with pytest.raises(ValueError, match="summing to 1"):
        mu_quantile(2.0 * pm, 0.5)


def test_prior_baseline_is_pmfs_prior_read_by_pmfs_rule():
    """The baseline is pmf's prior read by pmf's own quantile rule: with the prior as its whole posterior, pmf's median
    is the baseline's to the last digit (one owner of the quantile rule); its interval is wider at both ends, the
    grid's lowest cell and the guard's PRIOR_UPPER_MU, since no evidence excludes ice or the best dry asphalt."""
    from roadgrip.estimators.guard import PRIOR_UPPER_MU
    from roadgrip.estimators.pmf import N_MEM, N_OUT, O_LOWER, O_MU, O_UPPER, _output, _start

    base = prior_baseline()
    mem, out = np.zeros(N_MEM), np.zeros(N_OUT)
    _start(mem, False)  # a segment's start: the prior, before any sample
    _output(mem, 0.0, 0.0, True, out)
    assert base.mu_median == pytest.approx(out[O_MU], abs=1e-12)
    assert (base.mu_lower, base.mu_upper) == pytest.approx(
        (mu_quantile(PRIOR, 0.05), mu_quantile(PRIOR, 0.95)), abs=1e-12
    )
    assert out[O_LOWER] == pytest.approx(MU_GRID[0] - 0.5 * (MU_GRID[1] - MU_GRID[0]))
    assert out[O_LOWER] < 0.1 < base.mu_lower
    assert base.mu_upper < 1.1 < out[O_UPPER] == PRIOR_UPPER_MU


def test_catalogue_profile_keeps_the_entrys_nominal_values_and_the_drawn_drive_layout():
    drawn = COMPACT_HATCHBACK.replace(
        name="test-00007",
        mass_kg=1400.0,
        wheel_radius_m=0.31,
        drive="awd",
        front_drive_share=0.37,
        tire_front=TireParams(17.0, 12.0),
    )
    profile = catalogue_profile(COMPACT_HATCHBACK, drawn)
    assert profile.name == "test-00007"
    assert (profile.mass_kg, profile.wheel_radius_m) == (COMPACT_HATCHBACK.mass_kg, COMPACT_HATCHBACK.wheel_radius_m)
    assert profile.tire_front == COMPACT_HATCHBACK.tire_front
    assert (profile.drive, profile.front_drive_share) == ("awd", 0.5)  # the layout, with a nominal split
    same = catalogue_profile(COMPACT_HATCHBACK, drawn.replace(drive="fwd", front_drive_share=1.0))
    assert same == COMPACT_HATCHBACK.replace(name="test-00007")
