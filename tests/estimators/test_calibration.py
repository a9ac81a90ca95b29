import numpy as np

from roadgrip.estimators.calibration import UTILIZATION_EDGES, calibrate, interval, utilization_bin
from roadgrip.units import G_MPS2


def test_bins_follow_the_utilization_the_estimator_sees_and_abs_is_the_top_bin():
    mu = np.array([0.5, 0.5, 0.5, 0.5])
    accel = np.array([0.1, 0.3, 0.6, 0.1]) * 0.5 * G_MPS2
    bins = utilization_bin(accel, np.zeros(4), np.array([False, False, False, True]), mu)
    assert bins.tolist() == [0, 1, 2, 2] and len(UTILIZATION_EDGES) == 2


def test_conformal_intervals_cover_90_percent_per_bin_on_fresh_data():
    rng = np.random.default_rng(0)

    def draw(n):
        bins = rng.integers(0, 3, n)
        noise = np.array([0.25, 0.1, 0.02])[bins]  # estimates are worse where the tires do not work
        truth = rng.uniform(0.1, 1.0, n)
        return truth + rng.normal(0.0, noise), truth, bins

    calibration = calibrate(*draw(6000))
    pred, truth, bins = draw(30000)
    lower, upper = interval(pred, bins, calibration)
    inside = (truth >= lower) & (truth <= upper)
    for b in range(3):
        assert 0.88 <= inside[bins == b].mean() <= 0.92
    width = upper - lower
    assert width[bins == 0].mean() > 5 * width[bins == 2].mean(), "wide where not excited, narrow where excited"


def test_an_empty_bin_falls_back_on_all_the_calibration_data():
    pred = np.linspace(0, 1, 100)
    calibration = calibrate(pred, pred + 0.1, np.zeros(100, dtype=int))
    assert calibration["counts"] == [100, 0, 0]
    assert calibration["q_low"][2] == calibration["q_low"][0]
