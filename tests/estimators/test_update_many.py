"""`Estimator.update_many` against streaming (roadgrip/estimators/base.py): every estimator `load_estimator` takes by
name, fed a drive split at random points into runs, some runs through `update` one sample at a time and the others
through `update_many`, gives the estimates of one `update` per sample, to the last bit and with the same Python types,
and leaves the same state (state_to_dict). The drives are contract_drives.py's, with awkward samples mixed in where
hypothesis puts them: no speed (the guard's drag from the wheels), an optional flag absent or null, no GNSS channels,
a non-finite acceleration (the step rejects the sample; the guard's bound is NaN), a repeated timestamp (rejected: no
time step) and a gap that restarts the pmf's grid."""

from __future__ import annotations

import itertools
import json
import math

import pytest
from contract_drives import contract_drives
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roadgrip.estimators.base import EstimateRun
from roadgrip.estimators.learned import DEFAULT_MODEL, estimator_names, load_estimator

ESTIMATORS = {name: load_estimator(name) for name in estimator_names()}
DRIVES = contract_drives()
FAULTS = ("no_speed", "no_tcs_flag", "null_esc_flag", "no_channels", "nan_accel", "repeat_time", "gap")


def _with_faults(samples: tuple[dict, ...], faults: dict[int, str]) -> list[dict]:
    out, shift_ms = [], 0
    for k, sample in enumerate(samples):
        sample = {**sample, "timestamp_ms": sample["timestamp_ms"] + shift_ms}
        fault = faults.get(k)
        if fault == "no_speed":
            sample["speed_mps"] = None
        elif fault == "no_tcs_flag":
            del sample["tcs_active"]
        elif fault == "null_esc_flag":
            sample["esc_active"] = None
        elif fault == "no_channels":
            for channel in ("gnss_speed_mps", "gnss_speed_accuracy_mps", "drive_force_n", "brake_force_n"):
                sample.pop(channel, None)
        elif fault == "nan_accel":
            sample["accel_lon_mps2"] = math.nan
        elif fault == "repeat_time" and out:
            sample["timestamp_ms"] = out[-1]["timestamp_ms"]
        elif fault == "gap":
            shift_ms += 2_000
            sample["timestamp_ms"] += 2_000
        out.append(sample)
    return out


def _refused(run):
    """run's result, or the refusal it raised (a sample an estimator cannot read: the learned model's null speed)."""

    def wrapped(*args):
        try:
            return run(*args)
        except (TypeError, ValueError) as e:
            return type(e).__name__

    return wrapped


@_refused
def _streamed(estimator, drive, samples) -> tuple[list[dict], dict]:
    state = estimator.start(drive.vehicle)
    rows = [e.to_dict() for e in (estimator.update(state, s) for s in samples) if e is not None]
    return rows, estimator.state_to_dict(state)


@_refused
def _in_runs(estimator, drive, samples, cuts: list[int], one_by_one: list[bool]) -> tuple[list[dict], dict]:
    state = estimator.start(drive.vehicle)
    rows = []
    bounds = [0, *sorted(set(cuts)), len(samples)]
    for k, (start, stop) in enumerate(itertools.pairwise(bounds)):
        run = samples[start:stop]
        if one_by_one[k % len(one_by_one)]:
            rows += [e.to_dict() for e in (estimator.update(state, s) for s in run) if e is not None]
        else:
            found = estimator.update_many(state, run)
            assert isinstance(found, EstimateRun)
            assert [samples[start + i]["timestamp_ms"] for i in found.index.tolist()] == found.timestamp_ms.tolist()
            rows += found.rows()
    return rows, estimator.state_to_dict(state)


def _typed(rows: list[dict]) -> list[list]:
    """The rows as (key, repr) pairs: repr tells 1, 1.0 and True apart, gives a float to the last bit, and a NaN
    equals itself there."""
    return [[(k, repr(v)) for k, v in row.items()] for row in rows]


# the learned model (DEFAULT_MODEL) keeps the default loop over its own update and takes 1 s a drive: run by the
# in-runs-of-ten test below, not by hypothesis
@pytest.mark.parametrize("name", [name for name in ESTIMATORS if name != DEFAULT_MODEL])
@settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_update_many_over_random_runs_equals_streaming(name, data):
    estimator = ESTIMATORS[name]
    drive = DRIVES[data.draw(st.integers(0, len(DRIVES) - 1), label="drive")]
    n = len(drive.samples)
    faults = data.draw(st.dictionaries(st.integers(0, n - 1), st.sampled_from(FAULTS), max_size=12), label="faults")
    cuts = data.draw(st.lists(st.integers(1, n - 1), max_size=25), label="cuts")
    one_by_one = data.draw(st.lists(st.booleans(), min_size=1, max_size=4), label="one_by_one")
    samples = _with_faults(drive.samples, faults)
    expected = _streamed(estimator, drive, samples)
    got = _in_runs(estimator, drive, samples, cuts, one_by_one)
    if isinstance(expected, str):
        assert got == expected, "a sample update refuses refuses the run that holds it"
        return
    assert _typed(got[0]) == _typed(expected[0])
    assert json.dumps(got[1], sort_keys=True) == json.dumps(expected[1], sort_keys=True)


@pytest.mark.parametrize(
    "name", [pytest.param(n, marks=pytest.mark.slow) if n == DEFAULT_MODEL else n for n in ESTIMATORS]
)
def test_runs_of_ten_equal_streaming_on_every_drive(name):
    """The pipeline's case: each drive in runs of 10 (one message of a terminal)."""
    estimator = ESTIMATORS[name]
    for drive in DRIVES:
        samples = list(drive.samples)
        expected = _streamed(estimator, drive, samples)
        got = _in_runs(estimator, drive, samples, list(range(10, len(samples), 10)), [False])
        assert _typed(got[0]) == _typed(expected[0]), drive.vehicle_id
        assert json.dumps(got[1], sort_keys=True) == json.dumps(expected[1], sort_keys=True), drive.vehicle_id
        assert all(row["mu_proven"] is not None for row in got[0])


def test_an_empty_run_changes_nothing():
    estimator = ESTIMATORS["pmf"]
    state = estimator.start(DRIVES[0].vehicle)
    before = estimator.state_to_dict(state)
    found = estimator.update_many(state, [])
    assert len(found) == 0 and found.rows() == []
    assert estimator.state_to_dict(state) == before


def test_a_sample_lacking_a_required_field_refuses_the_run_by_name():
    estimator = ESTIMATORS["pmf"]
    state = estimator.start(DRIVES[0].vehicle)
    samples = [dict(s) for s in DRIVES[0].samples[:3]]
    del samples[2]["yaw_rate_radps"]
    with pytest.raises(ValueError, match="lacks the field 'yaw_rate_radps'"):
        estimator.update_many(state, samples)
