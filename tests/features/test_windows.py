import numpy as np
import pyarrow as pa
import pytest

from roadgrip.features.folds import grouped_folds, time_blocks
from roadgrip.features.windows import FEATURE_SETS, Scaler, feature_matrix, make_windows, segment_ids, window_ends


def test_windows_never_cross_segments():
    rng = np.random.default_rng(0)
    segments = np.repeat(np.arange(40), rng.integers(1, 30, 40))
    features = np.column_stack([np.arange(len(segments)), segments]).astype(np.float32)
    windows, ends = make_windows(features, segments, 10)
    assert len(windows) == sum(max(n - 9, 0) for n in np.bincount(segments))
    for w, end in zip(windows, ends):
        assert (w[:, 1] == segments[end]).all(), "every sample of a window belongs to the end sample's segment"
        assert (w[:, 0] == np.arange(end - 9, end + 1)).all(), "consecutive samples, ending at the labelled one"


def test_segment_ids_change_with_any_key():
    runs = np.array(["a", "a", "a", "b", "b", "a"])
    blocks = np.array([0, 0, 1, 1, 1, 1])
    assert segment_ids(runs, blocks).tolist() == [0, 0, 1, 2, 2, 3]


def test_window_length_must_be_positive():
    with pytest.raises(ValueError, match="window length must be >= 1, got 0"):
        window_ends(np.zeros(5), 0)


def test_scaler_is_fitted_on_what_it_is_given_only():
    train = np.random.default_rng(1).normal(5.0, 2.0, (200, 10, 3)).astype(np.float32)
    test = train + 100.0
    scaler = Scaler().fit(train)
    scaled = scaler.transform(train).reshape(-1, 3)
    assert np.allclose(scaled.mean(axis=0), 0.0, atol=1e-4) and np.allclose(scaled.std(axis=0), 1.0, atol=1e-3)
    assert scaler.transform(test).mean() > 10.0, "test data does not move the scaler"
    with pytest.raises(ValueError, match="not fitted"):
        Scaler().transform(train)


def test_feature_sets_and_missing_columns():
    assert "lateral_speed_mps" in FEATURE_SETS["paper"] and "lateral_speed_mps" not in FEATURE_SETS["terminal"]
    table = pa.table({c: [1.0, 2.0] for c in FEATURE_SETS["terminal"]})
    assert feature_matrix(table, "terminal").shape == (2, len(FEATURE_SETS["terminal"]))
    with pytest.raises(ValueError, match=r"needs column\(s\) \['lateral_speed_mps'\]"):
        feature_matrix(table, "paper")
    with pytest.raises(ValueError, match="feature_set must be one of"):
        feature_matrix(table, "imu")


def test_grouped_folds_never_share_a_run():
    runs = np.repeat([f"run-{k}" for k in range(10)], 37)
    folds = grouped_folds(runs, 5)
    assert len(folds) == 5
    seen = np.zeros(len(runs), dtype=int)
    for train, val in folds:
        assert not set(runs[train]) & set(runs[val])
        seen[val] += 1
    assert (seen == 1).all(), "every sample validates exactly once"
    with pytest.raises(ValueError, match="n_folds must be in"):
        grouped_folds(runs, 11)


def test_time_blocks():
    assert time_blocks(np.array([0.0, 3.9, 4.0, 39.9]), 4.0).tolist() == [0, 0, 1, 9]
