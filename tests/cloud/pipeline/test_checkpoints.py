"""Estimator state checkpoints (roadgrip/cloud/pipeline/checkpoints.py): each vehicle's estimator state, with pmf's
self-calibration, stored and found again after a restart of the service (SQLite and PostgreSQL) or of its ingest
processes; a state of another estimator, another profile or another layout is ignored; a database of an older version
without the table opens."""

from __future__ import annotations

import itertools
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import sqlalchemy as sa
from broker_fixtures import wait_until
from drives import patch_drive
from service_fixtures import ADMIN, START_MS, post, register, running_cloud

from roadgrip.cloud.pipeline.checkpoints import FLOATS, Checkpoints, pack_state, restore_state, unpack_state
from roadgrip.cloud.pipeline.pipeline import Pipeline, PipelineCounters
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import StorageUnavailable, open_storage
from roadgrip.cloud.storage.migrate import VERSION_TABLE
from roadgrip.estimators import pmf
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.demo import settle
from roadgrip.fleet.terminal import wire_samples
from roadgrip.vehicle.params import vehicle_by_name


def pmf_calibration(state) -> dict:
    """The guarded pmf state's calibration (PMFEstimator.calibration)."""
    return pmf.PMFEstimator().calibration(state["inner"])


# ------------------------------------------------------------------------------------------------- encoding
def test_pack_state_is_lossless_and_keeps_non_finite_numbers_out_of_the_json():
    floats = [0.1 * k + 1e-17 for k in range(40)]
    data = {
        "memory": floats,
        "short": [1.5, 2.5],
        "ints": list(range(30)),
        "nan_list": [1.0, math.nan],
        "rows": [[0.25] * 20, [1, "a"]],
        "name": "pmf",
        "t": 3.0,
        "flag": True,
        "none": None,
    }
    packed = pack_state(data)
    assert set(packed["memory"]) == {FLOATS} and set(packed["nan_list"]) == {FLOATS}
    assert packed["short"] == [1.5, 2.5] and packed["ints"] == list(range(30))  # short and integer lists stay
    json.dumps(packed, allow_nan=False)
    unpacked = unpack_state(json.loads(json.dumps(packed)))
    assert unpacked["memory"] == floats  # bit for bit
    assert unpacked["nan_list"][0] == 1.0 and math.isnan(unpacked["nan_list"][1])
    assert {k: v for k, v in unpacked.items() if k not in ("memory", "nan_list")} == {
        k: v for k, v in data.items() if k not in ("memory", "nan_list")
    }
    with pytest.raises(ValueError, match="non-finite"):
        pack_state({"t_prev": math.inf})


def test_a_pmf_state_packs_to_about_half_its_json_and_comes_back_exactly():
    estimator = load_estimator("pmf")
    state = estimator.start(vehicle_by_name("midsize-sedan"))
    for sample in wire_samples(patch_drive(0.9, 1, production=True), "car", START_MS)[:100]:
        estimator.update(state, sample)
    data = estimator.state_to_dict(state)
    packed = json.dumps(pack_state(data))
    assert len(packed) < 0.6 * len(json.dumps(data))
    again = estimator.state_from_dict(unpack_state(json.loads(packed)))
    np.testing.assert_array_equal(again["inner"].mem, state["inner"].mem)
    assert again["vehicle"] == state["vehicle"] and again["inner"].t_prev == state["inner"].t_prev


def test_a_restored_pmf_state_starts_a_new_segment_keeping_calibration_and_stiffness():
    """pmf's reset: the mu grid restarts from the prior, times the stiffness marginal it had; the calibration stays."""
    estimator = load_estimator("pmf")
    vehicle = vehicle_by_name("paper-suv")
    state = estimator.start(vehicle)
    for sample in wire_samples(patch_drive(0.2, 1, production=True), "car", START_MS):
        estimator.update(state, sample)
    stored = pack_state(estimator.state_to_dict(state))
    restored = restore_state(estimator, stored, vehicle)
    assert restored["inner"].mem[pmf.K_STARTED] == 0.0  # the next sample starts a segment
    assert pmf_calibration(restored) == pmf_calibration(state)
    mem = restored["inner"].mem.copy()
    pmf._start(mem, True)  # what the next update does first
    grid = mem[pmf.G0 : pmf.G0 + pmf.NM * pmf.NC].reshape(pmf.NM, pmf.NC)
    np.testing.assert_allclose(grid.sum(axis=1), pmf.PRIOR, rtol=1e-12)  # mu: back to the prior
    before = state["inner"].mem[pmf.G0 : pmf.G0 + pmf.NM * pmf.NC].reshape(pmf.NM, pmf.NC).sum(axis=0)
    np.testing.assert_allclose(grid.sum(axis=0), before / before.sum(), rtol=1e-12)  # stiffness: kept
    for key, index in pmf.CALIBRATION.items():
        assert mem[index] == state["inner"].mem[index], key


def test_a_stored_state_that_does_not_fit_is_ignored():
    estimator = load_estimator("pmf")
    suv, sedan = vehicle_by_name("paper-suv"), vehicle_by_name("midsize-sedan")
    good = pack_state(estimator.state_to_dict(estimator.start(suv)))
    assert restore_state(estimator, good, suv) is not None
    assert restore_state(estimator, good, sedan) is None  # another profile
    ekf = load_estimator("ekf")
    assert restore_state(estimator, pack_state(ekf.state_to_dict(ekf.start(suv))), suv) is None  # another estimator
    shorter = json.loads(json.dumps(good))
    shorter["inner"]["memory"] = pack_state([0.5] * 100)  # an older layout of pmf's memory
    assert restore_state(estimator, shorter, suv) is None
    assert restore_state(estimator, {"inner": good["inner"]}, suv) is None  # no profile to check it against
    assert restore_state(estimator, {"vehicle": good["vehicle"]}, suv) is None  # damaged


# ------------------------------------------------------------------------------------------------- storage
def test_estimator_states_are_kept_per_vehicle_and_estimator(storage):
    storage.put_estimator_states(
        [
            {"vehicle_id": "car-1", "estimator": "pmf", "state": {"a": 1}},
            {"vehicle_id": "car-1", "estimator": "ekf", "state": {"a": 2}},
            {"vehicle_id": "car-2", "estimator": "pmf", "state": {"a": 3}, "updated_ms": 5},
        ]
    )
    storage.put_estimator_states([{"vehicle_id": "car-1", "estimator": "pmf", "state": {"a": 4}}])  # replaced
    assert storage.estimator_states(["car-1", "car-2", "car-3"], "pmf") == {"car-1": {"a": 4}, "car-2": {"a": 3}}
    assert storage.estimator_states(["car-1"], "ekf") == {"car-1": {"a": 2}}
    assert storage.estimator_states([], "pmf") == {}
    rows = storage.estimator_state_rows()
    assert [(r["vehicle_id"], r["estimator"]) for r in rows] == [("car-1", "ekf"), ("car-1", "pmf"), ("car-2", "pmf")]
    assert rows[2]["updated_ms"] == 5
    with pytest.raises(TypeError, match="state of vehicle 'car-1' must be a dict"):
        storage.put_estimator_states([{"vehicle_id": "car-1", "estimator": "pmf", "state": [1]}])


def test_a_database_of_an_older_version_without_the_table_opens(storage_url, tmp_path):
    storage = open_storage(storage_url)
    storage.put_vehicle("car-1", vehicle_by_name("paper-suv").to_dict())
    with storage._transaction() as conn:  # the database as the version before checkpoints (and migrations) made it
        conn.execute(sa.text("DROP TABLE estimator_states"))
        conn.execute(sa.text(f"DROP TABLE {VERSION_TABLE}"))
    storage.close()
    storage = open_storage(storage_url)
    try:
        assert storage.vehicle_ids() == ["car-1"]
        storage.put_estimator_states([{"vehicle_id": "car-1", "estimator": "pmf", "state": {"a": 1}}])
        assert storage.estimator_states(["car-1"], "pmf") == {"car-1": {"a": 1}}
    finally:
        storage.close()


# ------------------------------------------------------------------------------------------------- the service
@pytest.mark.slow
def test_a_restarted_service_goes_on_from_each_vehicles_calibration(storage_url, tmp_path):
    """A vehicle drives, the service stops cleanly and starts again on the same database: the vehicle's estimator goes
    on from its calibration, its mu posterior restarted. A vehicle whose profile changed meanwhile starts afresh, and
    a service with another estimator leaves the pmf state alone."""
    run = patch_drive(0.2, 1, production=True)
    with running_cloud(storage_url, tmp_path, estimator="pmf") as (service, client):
        suv = register(client, "suv-1", "paper-suv")
        sedan = register(client, "sedan-1", "midsize-sedan")
        for vehicle_id, auth in (("suv-1", suv), ("sedan-1", sedan)):
            post(client, auth, wire_samples(run, vehicle_id, START_MS), chunk=50)
        settle(service)
        pipeline = service.ingest.pipeline
        calibration = pmf_calibration(pipeline._streams["suv-1"].state)
        assert pipeline.counters.checkpoints_written == 0  # 30 s of data: none due yet
    assert calibration["accel_bias_weight_s"] > 10 and calibration["radius_ratio_weight_s"] > 5
    assert pipeline.counters.checkpoints_written == 2  # both, at the stop

    storage = open_storage(storage_url)
    rows = {row["vehicle_id"]: row for row in storage.estimator_state_rows()}
    assert {(v, row["estimator"]) for v, row in rows.items()} == {("suv-1", "pmf"), ("sedan-1", "pmf")}
    estimator = load_estimator("pmf")
    assert pmf_calibration(estimator.state_from_dict(unpack_state(rows["suv-1"]["state"]))) == calibration
    storage.put_vehicle("sedan-1", vehicle_by_name("compact-hatchback").to_dict())  # a new profile
    storage.close()

    later = {v: wire_samples(run, v, START_MS + 120_000) for v in ("suv-1", "sedan-1")}
    with running_cloud(storage_url, tmp_path, estimator="pmf") as (service, client):
        post(client, suv, later["suv-1"][:1])
        post(client, sedan, later["sedan-1"][:1])
        settle(service)
        pipeline = service.ingest.pipeline
        assert pipeline.counters.checkpoints_restored == 1
        live = pipeline._streams["suv-1"].state
        expected = estimator.state_from_dict(unpack_state(rows["suv-1"]["state"]))
        estimator.reset(expected)  # restored, then a new segment
        estimate = estimator.update(expected, later["suv-1"][0])
        np.testing.assert_array_equal(live["inner"].mem, expected["inner"].mem)
        stored = service.storage.estimates("suv-1", start_ms=START_MS + 120_000)
        assert [(e["mu"], e["mu_lower"], e["mu_upper"]) for e in stored] == [
            (estimate.mu, estimate.mu_lower, estimate.mu_upper)
        ]
        now = pmf_calibration(live)
        assert {k: now[k] for k in pmf.CALIBRATION} == {k: calibration[k] for k in pmf.CALIBRATION}
        fresh = estimator.start(vehicle_by_name("compact-hatchback"))
        estimator.update(fresh, later["sedan-1"][0])
        np.testing.assert_array_equal(pipeline._streams["sedan-1"].state["inner"].mem, fresh["inner"].mem)

    with running_cloud(storage_url, tmp_path, estimator="ekf") as (service, client):
        post(client, suv, later["suv-1"][1:3])
        settle(service)
        assert service.ingest.pipeline.counters.checkpoints_restored == 0
    storage = open_storage(storage_url)
    try:
        after = {(row["vehicle_id"], row["estimator"]): row for row in storage.estimator_state_rows()}
        assert set(after) == {("suv-1", "pmf"), ("suv-1", "ekf"), ("sedan-1", "pmf")}
        assert after[("suv-1", "ekf")]["state"]["inner"]["estimator"] == "ekf"
        # the pmf state of suv-1 is the one the second run stored at its stop: its one new sample on top
        assert unpack_state(after[("suv-1", "pmf")]["state"])["inner"]["t_prev"] == later["suv-1"][0]["timestamp_ms"]
    finally:
        storage.close()


def test_states_are_checkpointed_every_interval_in_bounded_rounds_and_all_at_the_stop(tmp_path):
    settings = Settings(data_dir=tmp_path, mqtt="off", flush_interval_s=0.01, reorder_window_s=0.05)
    storage = open_storage(settings.storage_url)
    batches: list[tuple[bool, list[tuple[str, float]]]] = []  # (at the stop, [(vehicle, t_prev of its state)])
    put = storage.put_estimator_states
    stopping = False

    def recorded(rows):
        batches.append((stopping, [(r["vehicle_id"], unpack_state(r["state"])["inner"]["t_prev"]) for r in rows]))
        put(rows)

    storage.put_estimator_states = recorded
    estimator = load_estimator("pmf")
    pipeline = Pipeline(storage, settings, estimator, SimpleNamespace(stored=lambda *a: None, tick=lambda final: None))
    pipeline.checkpoints.interval_ms, pipeline.checkpoints.round_s, pipeline.checkpoints.per_round = 10_000, 0.0, 2
    vehicles = ["car-a", "car-b", "car-c"]
    streams = {v: wire_samples(patch_drive(0.9, 3), v, START_MS) for v in vehicles}
    last_ms = {v: streams[v][-1]["timestamp_ms"] for v in vehicles}
    pipeline.start()
    try:
        for k in range(0, 300, 10):  # 1 s of each vehicle's data every 10 ms
            futures = [pipeline.submit(v, streams[v][k : k + 10]) for v in vehicles]
            for future in futures:
                future.result(timeout=30)
        wait_until(
            lambda: all(pipeline._streams[v].last_estimated_ms == last_ms[v] for v in vehicles),
            10,
            "every sample estimated",
        )
    finally:
        stopping = True
        pipeline.stop()
    during = [batch for at_stop, batch in batches if not at_stop]
    assert during and all(len(batch) <= 2 for batch in during)  # rounds of at most per_round vehicles
    for v in vehicles:  # every 10 s of data: the drive lasts 30 s
        times = [t for batch in during for vehicle_id, t in batch if vehicle_id == v]
        assert len(times) >= 2 and times[0] >= START_MS + 5_000, times  # the first after 5-10 s (vehicle_id)
        assert all(b - a >= 10_000 for a, b in itertools.pairwise(times)), times
    # at the stop, every vehicle estimated since its last checkpoint: each stored state is its newest
    assert [len(batch) for at_stop, batch in batches if at_stop] in ([], [1], [2], [3])
    stored = storage.estimator_states(vehicles, "pmf")
    assert {v: unpack_state(stored[v])["inner"]["t_prev"] for v in vehicles} == last_ms
    assert pipeline.counters.checkpoints_written == sum(len(batch) for _, batch in batches)
    storage.close()


def test_while_storage_is_down_the_due_vehicles_wait_for_the_next_round():
    class Flaky:
        def __init__(self):
            self.down, self.rows = True, []

        def put_estimator_states(self, rows):
            if self.down:
                raise StorageUnavailable("down")
            self.rows += rows

    storage, estimator = Flaky(), load_estimator("ekf")
    counters = PipelineCounters()
    checkpoints = Checkpoints(storage, estimator, counters, round_s=0.0)
    stream = SimpleNamespace(
        state=estimator.start(vehicle_by_name("paper-suv")),
        last_estimated_ms=70_000,
        checkpoint_at_ms=60_000.0,
        written_ms=None,
    )
    checkpoints.due("car-1", stream)
    checkpoints.write_due({"car-1": stream})
    assert storage.rows == [] and stream.checkpoint_at_ms == math.inf and counters.checkpoints_written == 0
    storage.down = False
    checkpoints.write_due({"car-1": stream})
    assert [r["vehicle_id"] for r in storage.rows] == ["car-1"] and stream.written_ms == 70_000
    assert stream.checkpoint_at_ms == 130_000 and counters.checkpoints_written == 1
    checkpoints.write_due({"car-1": stream})  # nothing due any more
    assert len(storage.rows) == 1
    checkpoints.write_all({"car-1": stream})  # nothing estimated since
    assert len(storage.rows) == 1


@pytest.mark.slow
def test_ingest_processes_store_and_restore_the_states_of_their_own_vehicles(tmp_path):
    from tests.cloud.serve.test_shards import ids_on_each_shard, running_sharded

    url = f"sqlite:///{tmp_path / 'roadgrip.sqlite'}"
    ids = ids_on_each_shard("ckpt", 1)
    run = patch_drive(0.9, 2)
    with running_sharded(url, tmp_path, estimator="pmf") as (service, client):
        auths = [register(client, v) for v in ids]
        for auth in auths:
            post(client, auth, wire_samples(run, auth[0], START_MS)[:100], chunk=50)
        settle(service)
    storage = open_storage(url)
    try:
        assert {row["vehicle_id"] for row in storage.estimator_state_rows()} == set(ids)
    finally:
        storage.close()
    with running_sharded(url, tmp_path, estimator="pmf") as (service, client):
        for auth in auths:
            post(client, auth, wire_samples(run, auth[0], START_MS + 60_000)[:5])
        settle(service)
        wait_until(
            lambda: client.get("/v1/health", auth=ADMIN).json()["pipeline"]["checkpoints_restored"] == 2,
            10,
            "both vehicles restored, one in each ingest process",
        )
