"""The estimator contract (issue 24): one set of checks that every estimator the project ships must pass, as
`load_estimator` gives it (with the physics guard), as scikit-learn's check_estimator does for its estimators.

The estimators are `estimator_names()`, the one list `load_estimator` takes by name (roadgrip/estimators/learned.py):
an estimator added there is checked here. The inputs are contract_drives.py's short production drives (ABS braking,
cornering, calm cruising; three vehicle profiles). The checks:

- schema: batch output in the columns and types of roadgrip.data.schema.ESTIMATE's first eight fields, mu_proven
  filled (the guard adds it); one row per judged sample, with its input's vehicle_id and timestamp_ms, in order;
- invariants: 0 <= mu_lower <= mu <= mu_upper, finite, on every row, batch and streaming;
- the force bound: mu >= (|a_road| - 2 sigma_a) / g, computed here from the input's own accelerations as
  docs/PRODUCTION.md states it (drag and the rolled accelerometer taken out: the raw sqrt(a_x^2 + a_y^2) overstates
  the road's force by up to 7 % of a_y, and asks 0.016 more than a cornering car proves);
- state round trip: a state saved mid-stream through the cloud's checkpoint encoding and loaded into a fresh
  estimator gives the rest of the stream exactly as an uninterrupted run;
- batch = streaming: one estimate_batch over a drive equals the stream fed in chunks of 1, 7, 50 samples and whole,
  the state crossing each chunk boundary through the checkpoint encoding into the other of two estimators; to the
  last bit, but for the learned model (float32: within 1e-5, and its exact case an xfail);
- determinism: two fresh estimators give identical output on the same input, batch and streaming;
- vehicles kept apart: one estimator streaming the three vehicles interleaved gives each the output it gets alone.
  (estimate_batch takes one vehicle's table by its interface; `roadgrip estimate` splits a file by vehicle.)
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pytest
from contract_drives import contract_drives

from roadgrip.cloud.pipeline.checkpoints import pack_state, unpack_state
from roadgrip.data.schema import ESTIMATE
from roadgrip.estimators.learned import DEFAULT_MODEL, estimator_names, load_estimator
from roadgrip.estimators.vehicle_model import roll_per_lateral_accel
from roadgrip.units import G_MPS2
from roadgrip.vehicle.dynamics import AIR_DENSITY_KGPM3

# docs/PRODUCTION.md, "The physics guard": the bound is (|a_road| - 2 sigma_a) / g with sigma_a = 0.3 m/s^2
ACCEL_SIGMA_MPS2 = 0.3
K_SIGMA = 2.0
FLOAT_FIELDS = ("mu", "mu_lower", "mu_upper", "mu_proven")
CHUNK_SIZES = (1, 7, 50, None)  # None: the whole drive in one chunk (plain streaming)
WARM_UP_SAMPLES = 10  # an estimator may start judging this late (the learned model's window: 1 s)


@dataclass(frozen=True)
class Case:
    """An estimator of the suite; `batch_tolerance`: how far its batch numbers may lie from its streamed ones (0:
    identical). A float32 network gives its batch of windows and a single window different roundings (1e-7), which
    the guard and the interval pass on; test_learned.py holds the learned models to 1e-5 there."""

    name: str
    batch_tolerance: float = 0.0


CASES = [Case(name, 1e-5 if name == DEFAULT_MODEL else 0.0) for name in estimator_names()]
IDS = [case.name for case in CASES]


def test_the_suite_covers_every_estimator_load_estimator_takes_by_name():
    assert set(estimator_names()) >= {"pmf", "ekf", "ukf", DEFAULT_MODEL}
    for name in ("fusion", "ekf-magic"):
        with pytest.raises(ValueError, match="--model must be a model file"):
            load_estimator(name)


# ------------------------------------------------------------------------------------------------ running them
def _batch(estimator, drive) -> list[dict]:
    return estimator.estimate_batch(drive.table, drive.segments, drive.vehicle).to_pylist()


def _checkpoint(estimator, state) -> dict:
    """The state as the cloud stores it: state_to_dict, packed (checkpoints.py), JSON text, and back."""
    return unpack_state(json.loads(json.dumps(pack_state(estimator.state_to_dict(state)))))


def _stream(estimator, drive, samples=None, state=None) -> list[dict]:
    state = estimator.start(drive.vehicle) if state is None else state
    out = [estimator.update(state, sample) for sample in (drive.samples if samples is None else samples)]
    return [e.to_dict() for e in out if e is not None]


def _stream_in_chunks(estimators, drive, size) -> list[dict]:
    """The drive streamed `size` samples at a time, the state handed from one estimator to the other between chunks."""
    out = []
    state = estimators[0].start(drive.vehicle)
    for k, start in enumerate(range(0, len(drive.samples), size)):
        estimator = estimators[k % 2]
        if k:
            state = estimator.state_from_dict(_checkpoint(estimators[(k - 1) % 2], state))
        out += _stream(estimator, drive, drive.samples[start : start + size], state)
    return out


def _assert_same(got: list[dict], expected: list[dict], tolerance: float = 0.0) -> None:
    assert len(got) == len(expected)
    for g, e in zip(got, expected):
        if tolerance == 0.0:
            assert g == e
            continue
        assert {k: v for k, v in g.items() if k not in FLOAT_FIELDS} == {
            k: v for k, v in e.items() if k not in FLOAT_FIELDS
        }
        for key in FLOAT_FIELDS:
            assert g[key] == pytest.approx(e[key], abs=tolerance), (key, g["timestamp_ms"])


@pytest.fixture(scope="module")
def drives():
    return contract_drives()


@pytest.fixture(scope="module", params=CASES, ids=IDS)
def case(request):
    return request.param


@pytest.fixture(scope="module")
def estimator(case):
    return load_estimator(case.name)


@pytest.fixture(scope="module")
def batches(estimator, drives):
    return {d.vehicle_id: _batch(estimator, d) for d in drives}


@pytest.fixture(scope="module")
def streams(estimator, drives):
    return {d.vehicle_id: _stream(estimator, d) for d in drives}


# ------------------------------------------------------------------------------------------------ the checks
def test_batch_output_has_the_estimate_schema(estimator, drives):
    fields = [pa.field(c.name, c.type, nullable=not c.required) for c in ESTIMATE[:8]]
    for drive in drives:
        out = estimator.estimate_batch(drive.table, drive.segments, drive.vehicle)
        assert out.schema == pa.schema(fields), drive.vehicle_id
        assert out["mu_proven"].null_count == 0, "the guard adds mu_proven to every estimate"


def test_one_row_per_judged_sample_with_its_vehicle_and_timestamp(batches, streams, drives):
    for drive in drives:
        inputs = [s["timestamp_ms"] for s in drive.samples]
        for rows in (batches[drive.vehicle_id], streams[drive.vehicle_id]):
            judged = [r["timestamp_ms"] for r in rows]
            # None only "while the estimator cannot judge yet" (base.py): the learned model's first window, 1 s
            assert judged == inputs[len(inputs) - len(judged) :], "the input's timestamps, in order, from some start"
            assert len(judged) >= len(inputs) - WARM_UP_SAMPLES
            assert {r["vehicle_id"] for r in rows} == {drive.vehicle_id}


def test_streamed_estimates_have_the_schema_fields_and_types(streams, estimator):
    types = {
        "vehicle_id": str,
        "timestamp_ms": int,
        "mu": float,
        "mu_lower": float,
        "mu_upper": float,
        "excited": bool,
        "estimator": str,
        "mu_proven": float,
    }
    for rows in streams.values():
        for row in rows:
            assert list(row) == [c.name for c in ESTIMATE[:8]]
            assert {k: type(v) for k, v in row.items()} == types
            assert row["estimator"] == estimator.name


def test_every_row_is_finite_and_ordered(batches, streams):
    for rows in [*batches.values(), *streams.values()]:
        for r in rows:
            assert all(math.isfinite(r[k]) for k in FLOAT_FIELDS), r
            assert 0.0 <= r["mu_lower"] <= r["mu"] <= r["mu_upper"], r


def _force_bound(drive, timestamps) -> np.ndarray:
    """(|a_road| - 2 sigma_a) / g from the drive's own accelerations (docs/PRODUCTION.md): the accelerometer reads
    the road's force and the air's (drag D(v) = 1/2 rho c_d A v^2 decelerates the car without the road's help), and
    on a rolled body a_y (1 + g k_phi), k_phi the roll per lateral acceleration."""
    at = {s["timestamp_ms"]: s for s in drive.samples}
    ax, ay, v = (np.array([at[t][c] for t in timestamps]) for c in ("accel_lon_mps2", "accel_lat_mps2", "speed_mps"))
    p = drive.vehicle
    drag_mps2 = 0.5 * AIR_DENSITY_KGPM3 * p.drag_coefficient * p.frontal_area_m2 * v * v / p.mass_kg
    road = np.hypot(ax + drag_mps2, ay / (1.0 + G_MPS2 * roll_per_lateral_accel(p)))
    return (road - K_SIGMA * ACCEL_SIGMA_MPS2) / G_MPS2


def test_mu_is_never_below_what_the_car_proves(batches, streams, drives):
    for drive in drives:
        for rows in (batches[drive.vehicle_id], streams[drive.vehicle_id]):
            bound = _force_bound(drive, [r["timestamp_ms"] for r in rows])
            mu = np.array([r["mu"] for r in rows])
            assert (mu >= bound - 1e-9).all(), (drive.vehicle_id, float((bound - mu).max()))
    hard = _force_bound(drives[1], [s["timestamp_ms"] for s in drives[1].samples])
    assert hard.max() > 0.5, "the corner must reach a bound that an estimator could miss"


def test_a_state_saved_mid_stream_continues_in_a_fresh_estimator(case, streams, drives):
    """Cut inside the learned model's first window (5), mid-ABS (45), mid-corner and near its end."""
    cuts = {"abs-brake": (5, 45), "corner": (60, 115), "cruise": (75,)}
    for drive in drives:
        uninterrupted = streams[drive.vehicle_id]
        for cut in cuts[drive.vehicle_id]:
            first = load_estimator(case.name)
            state = first.start(drive.vehicle)
            head = _stream(first, drive, drive.samples[:cut], state)
            fresh = load_estimator(case.name)
            tail = _stream(fresh, drive, drive.samples[cut:], fresh.state_from_dict(_checkpoint(first, state)))
            _assert_same(head + tail, uninterrupted)


@pytest.mark.parametrize("size", CHUNK_SIZES, ids=[f"chunk{s or 'all'}" for s in CHUNK_SIZES])
def test_batch_equals_streaming_in_chunks(case, batches, drives, size):
    estimators = (load_estimator(case.name), load_estimator(case.name))
    for drive in drives:
        streamed = _stream_in_chunks(estimators, drive, size or len(drive.samples))
        _assert_same(streamed, batches[drive.vehicle_id], case.batch_tolerance)


FLOAT32_ROUNDING = pytest.mark.xfail(
    strict=True,
    reason="a float32 network rounds a batch of windows and a single "
    "window differently (6e-8 on these drives): equal within batch_tolerance only",
)


@pytest.mark.parametrize(
    "name", [pytest.param(c.name, marks=FLOAT32_ROUNDING) if c.batch_tolerance else c.name for c in CASES], ids=IDS
)
def test_batch_equals_streaming_to_the_last_bit(name, drives):
    estimator = load_estimator(name)
    for drive in drives:
        _assert_same(_stream(estimator, drive), _batch(estimator, drive))


def test_two_fresh_estimators_give_identical_output(case, batches, streams, drives):
    again = load_estimator(case.name)
    for drive in drives:
        _assert_same(_batch(again, drive), batches[drive.vehicle_id])
        _assert_same(_stream(again, drive), streams[drive.vehicle_id])


def test_vehicles_streamed_together_are_kept_apart(case, streams, drives):
    """One estimator, the three vehicles' samples interleaved (as the cloud's pipeline feeds them)."""
    estimator = load_estimator(case.name)
    states = {d.vehicle_id: estimator.start(d.vehicle) for d in drives}
    together = {d.vehicle_id: [] for d in drives}
    interleaved = sorted((s for d in drives for s in d.samples), key=lambda s: s["timestamp_ms"])
    for sample in interleaved:
        estimate = estimator.update(states[sample["vehicle_id"]], sample)
        if estimate is not None:
            together[sample["vehicle_id"]].append(estimate.to_dict())
    for drive in drives:
        _assert_same(together[drive.vehicle_id], streams[drive.vehicle_id])
