"""The fan-out split into its vehicles' part and its regions' part (issue 17 item 3), without a broker: serve's `Fanout`
(one region holding everything) and the cluster's parts (`VehicleFanout` per worker, `Regions` per region owner, the
region stage's messages in between) raise the same warnings and build the same map from the same rounds; a region's
new owner goes on from the database (map cells, active warnings) and cancels the warning as the first would have; a
repeated message counts once; an owner whose queue was taken since stores nothing."""

from __future__ import annotations

import dataclasses
import json

import h3
import pytest
from fake_clock import FakeClock

from roadgrip.cloud.cluster.map_cells import stored_friction_map
from roadgrip.cloud.cluster.regions import Regions, region_messages
from roadgrip.cloud.domain.cells import region_of
from roadgrip.cloud.formats.denm import decode_denm_uper
from roadgrip.cloud.pipeline.fanout import Fanout, VehicleFanout, new_friction_map, new_warning_engine
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Fenced, open_storage
from roadgrip.cloud.transport.mqtt import WARNINGS_TOPIC, WARNINGS_UPER_TOPIC

T0_MS = 1_768_464_000_000
HEBEI = (38.0, 114.5)
MUNICH = (48.1, 11.5)
STEP_M = 2.0  # 20 m/s at 10 Hz
PATCH = (300, 450)  # samples on ice


def drive(vehicle: str, start_ms: int, origin: tuple[float, float], icy: bool, n: int = 700) -> list[dict]:
    """A vehicle driving east, braking all along (every estimate excited): ice on samples PATCH when `icy`."""
    lat, lon0 = origin
    rows = []
    for i in range(n):
        lon = lon0 + i * STEP_M / 111_320.0 / 0.75
        on_ice = icy and PATCH[0] <= i < PATCH[1]
        mu, lo, hi = (0.12, 0.05, 0.25) if on_ice else (0.9, 0.7, 1.2)
        rows.append(
            {
                "vehicle_id": vehicle,
                "timestamp_ms": start_ms + 100 * i,
                "latitude_deg": lat,
                "longitude_deg": lon,
                "mu": mu,
                "mu_lower": lo,
                "mu_upper": hi,
                "excited": True,
                "estimator": "pmf",
                "mu_proven": None,
                "h3_cell": h3.latlng_to_cell(lat, lon, 10),
            }
        )
    return rows


def rounds(rows: list[dict], round_ms: int = 1000) -> list[tuple[list[dict], int]]:
    """Rows in rounds of round_ms of data, each with its newest timestamp (the rounds a pipeline stores)."""
    rows = sorted(rows, key=lambda r: (r["timestamp_ms"], r["vehicle_id"]))
    out, start = [], rows[0]["timestamp_ms"]
    while rows:
        batch = [r for r in rows if r["timestamp_ms"] < start + round_ms]
        rows = rows[len(batch) :]
        if batch:
            out.append((batch, max(r["timestamp_ms"] for r in batch)))
        start += round_ms
    return out


def scenario() -> list[tuple[list[dict], int]]:
    """Two vehicles brake on a patch of ice in each of two regions; two minutes later a dry vehicle in each region
    (their data clock ends the first passes)."""
    rows = []
    for origin, tag in ((HEBEI, "h"), (MUNICH, "m")):
        rows += drive(f"{tag}-ice-1", T0_MS, origin, icy=True) + drive(f"{tag}-ice-2", T0_MS + 5_000, origin, True)
        rows += drive(f"{tag}-far", T0_MS + 120_000, (origin[0] + 0.01, origin[1]), icy=False, n=50)
    return rounds(rows)


def without_action_id(topic: str, payload: bytes) -> str:
    """A published DENM, JSON or (on its own topic) UPER-encoded, without its ActionID."""
    denm = decode_denm_uper(payload) if topic == WARNINGS_UPER_TOPIC else json.loads(payload)
    del denm["denm"]["management"]["actionID"]
    return json.dumps(denm, sort_keys=True)


def assert_same_cells(got: list, want: list) -> None:
    """Equal summaries, floats to 1e-12 (the regions' maps sum the same evidence in another order)."""
    assert [c.cell for c in got] == [c.cell for c in want]
    for g, w in zip(got, want):
        for name, value in dataclasses.asdict(w).items():
            assert getattr(g, name) == (pytest.approx(value, rel=1e-12) if isinstance(value, float) else value)


class Regional:
    """The cluster's parts in one process: a vehicles' part whose region sink is the region stage's messages, applied
    to `regions` (what the broker does between a worker and the region owners)."""

    def __init__(self, regions: Regions):
        self.regions = regions

    def estimates(self, rows: list[dict], newest_data_ms: int) -> None:
        for region, message in region_messages(rows, newest_data_ms, self.regions.region_resolution).items():
            self.regions.apply(region, message)


@pytest.fixture
def settings(tmp_path):
    return Settings(data_dir=tmp_path, map_clock="data")


def test_serves_one_region_and_the_clusters_regions_give_the_same_warnings_and_map(settings, tmp_path):
    serve_storage = open_storage(f"sqlite:///{tmp_path / 'serve.db'}")
    cluster_storage = open_storage(f"sqlite:///{tmp_path / 'cluster.db'}")
    serve_denms, cluster_denms = [], []
    serve = Fanout(
        serve_storage,
        settings,
        new_friction_map(settings),
        new_warning_engine(settings),
        publish=lambda topic, payload: serve_denms.append((topic, without_action_id(topic, payload))),
    )
    regions = Regions(
        settings,
        cluster_storage,
        publish=lambda topic, payload: cluster_denms.append((topic, without_action_id(topic, payload))),
    )
    worker = VehicleFanout(settings, Regional(regions))
    for rows, newest in scenario():
        serve.stored(rows, newest + 50.0, newest)
        worker.stored(rows, newest + 50.0, newest)
    regions.save()
    assert len({region[:3] for region in regions.held}) == 2  # Hebei's and Munich's base cells, far apart
    serve_warnings = serve_storage.warnings()
    assert {region_of(w["cell"], settings.region_resolution)[:3] for w in serve_warnings} == {
        region[:3] for region in regions.held
    }
    cluster_warnings = cluster_storage.warnings()
    # one ActionID per warning across the regions (the database numbers them), in the order they were raised
    numbers = [w["message"]["event"].pop("action_sequence_number") for w in cluster_warnings]
    assert sorted(numbers) == list(range(len(cluster_warnings)))
    for w in cluster_warnings + serve_warnings:
        w["message"]["event"].pop("action_sequence_number", None)
        del w["message"]["denm"]["denm"]["management"]["actionID"]
    assert cluster_warnings == serve_warnings
    now_ms = serve.now_ms()
    cells = serve.friction_map.cells(now_ms)
    assert_same_cells(
        sorted((c for r in regions.held.values() for c in r.friction_map.cells(now_ms)), key=lambda c: c.cell), cells
    )
    assert_same_cells(stored_friction_map(cluster_storage, settings, now_ms).cells(now_ms), cells)
    assert len(serve_denms) > 2 * len(serve_warnings)  # raised and refreshed, each as JSON and UPER
    json_denms = [json.loads(d) for t, d in serve_denms if t == WARNINGS_TOPIC]
    uper_denms = [json.loads(d) for t, d in serve_denms if t == WARNINGS_UPER_TOPIC]
    assert uper_denms == [{k: d[k] for k in ("header", "denm")} for d in json_denms]  # one message, two renderings
    assert sorted(cluster_denms) == sorted(serve_denms)
    serve_storage.close()
    cluster_storage.close()


def test_a_regions_new_owner_goes_on_from_the_database_and_counts_a_repeated_message_once(settings, tmp_path):
    storage = open_storage(f"sqlite:///{tmp_path / 'cluster.db'}")
    first = Regions(settings, storage)
    messages = [
        (region, message)
        for rows, newest in scenario()
        for region, message in region_messages(rows, newest, settings.region_resolution).items()
    ]
    for region, message in messages:
        first.apply(region, message)
    first.save()
    raised = storage.warnings(active_only=True)
    assert raised
    now_ms = max(r.now_ms() for r in first.held.values())
    taken_over = Regions(settings, storage)  # the first owner died after its last save
    region, message = messages[-1]
    taken_over.apply(region, message)  # redelivered: its estimates are in the restored cells already
    assert taken_over.dropped == len(message["estimates"])
    assert_same_cells(
        taken_over.region(region).friction_map.cells(now_ms), first.held[region].friction_map.cells(now_ms)
    )
    # later, a vehicle brakes on dry road where the ice was: the restored warnings are cancelled
    later = max(m["newest_data_ms"] for _, m in messages) + 120_000
    for origin, tag in ((HEBEI, "h"), (MUNICH, "m")):
        for rows, newest in rounds(
            drive(f"{tag}-dry", later, origin, icy=False)
            + drive(f"{tag}-far-2", later + 120_000, (origin[0] + 0.01, origin[1]), False, 50)
        ):
            for region, message in region_messages(rows, newest, settings.region_resolution).items():
                taken_over.apply(region, message)
    taken_over.save()
    after = {w["warning_id"]: w for w in storage.warnings()}
    for w in raised:
        assert after[w["warning_id"]]["status"] == "cancelled", w["cell"]
        assert after[w["warning_id"]]["message"]["event"]["reason"] == "recovered"
    storage.close()


def test_an_owner_whose_region_queue_was_taken_since_stores_nothing(settings, tmp_path):
    storage = open_storage(f"sqlite:///{tmp_path / 'cluster.db'}")
    stale = Regions(settings, storage, fence=(0, storage.take_region_queue(0, "a")))
    storage.take_region_queue(0, "b")
    with pytest.raises(Fenced):
        for rows, newest in scenario():
            for region, message in region_messages(rows, newest, settings.region_resolution).items():
                stale.apply(region, message)
        stale.save()
    assert storage.warnings() == [] and storage.map_cells() == []
    storage.close()


def test_a_region_without_traffic_ends_passes_on_the_servers_clock(tmp_path):
    """A vehicle stops on the ice: nothing more arrives in its region, yet its last pass ends pass_gap_s later on the
    server's clock (a region owner's tick) and raises there, as serve's next round of any vehicle would."""
    settings = Settings(data_dir=tmp_path, map_clock="wall", warning_pass_gap_s=1.0)
    storage = open_storage(f"sqlite:///{tmp_path / 'cluster.db'}")
    regions = Regions(settings, storage)
    clock = FakeClock(T0_MS / 1000)  # the server's clock; the last sample 0.1 s before it
    rows = drive("stopped", T0_MS - 100 * PATCH[1], HEBEI, icy=True, n=PATCH[1])
    for region, message in region_messages(rows, rows[-1]["timestamp_ms"], settings.region_resolution).items():
        regions.region(region).clock = clock
        regions.apply(region, message)
    last_cell = rows[-1]["h3_cell"]
    assert last_cell not in {w["cell"] for w in storage.warnings()}  # its pass there is still open
    regions.tick()
    clock.advance(0.5)
    regions.tick()
    assert last_cell not in {w["cell"] for w in storage.warnings()}  # not yet pass_gap_s
    clock.advance(0.6)
    regions.tick()
    assert last_cell in {w["cell"] for w in storage.warnings(active_only=True)}
    storage.close()


def test_the_settings_make_the_map_and_the_engine_in_one_place_each():
    settings = Settings(
        h3_resolution=9,
        map_half_life_s=300.0,
        map_max_age_s=1800.0,
        warning_threshold_mu=0.35,
        warning_min_low_passes=2,
        warning_min_dry_passes=3,
        warning_pass_gap_s=20.0,
        warning_min_excited_per_pass=4,
        warning_validity_s=900.0,
        station_id=7,
    )
    fmap = new_friction_map(settings)
    assert (fmap.resolution, fmap.half_life_s, fmap.max_age_s, fmap.pass_gap_s) == (9, 300.0, 1800.0, 20.0)
    engine = new_warning_engine(settings, action_sequence=len)
    assert (
        engine.resolution,
        engine.threshold_mu,
        engine.min_low_passes,
        engine.min_dry_passes,
        engine.pass_gap_s,
        engine.min_excited_per_pass,
        engine.validity_s,
        engine.station_id,
        engine.action_sequence,
    ) == (9, 0.35, 2, 3, 20.0, 4, 900.0, 7, len)
    swept = new_warning_engine(settings, threshold_mu=0.5, min_low_passes=1)  # a study's overrides
    assert (swept.threshold_mu, swept.min_low_passes, swept.validity_s, swept.action_sequence) == (0.5, 1, 900.0, None)
    assert new_friction_map(settings, half_life_s=60.0).half_life_s == 60.0


def test_a_regions_new_owner_applies_what_the_broker_returned_out_of_order_in_time_order(settings, tmp_path):
    """At a region queue's hand-over RabbitMQ returns the previous owner's unacknowledged messages out of order
    (results/trials/cluster/handover_order.py): one by one, a vehicle's older estimates behind its newer ones are
    dropped as repeats; held and applied together (`apply_held`), none is, and the map is the one of the messages
    in order."""
    messages = [
        (region, message)
        for rows, newest in scenario()
        for region, message in region_messages(rows, newest, settings.region_resolution).items()
    ]
    returned = messages[5:10][::-1] + messages[10:]  # the first five applied before the hand-over
    owners = {}
    for name in ("in order", "one by one", "held"):
        storage = open_storage(f"sqlite:///{tmp_path / (name + '.db')}")
        before = Regions(settings, storage)
        for region, message in messages[:5]:
            before.apply(region, message)
        before.save()
        owners[name] = Regions(settings, storage)
    for region, message in messages[5:]:
        owners["in order"].apply(region, message)
    for region, message in returned:
        owners["one by one"].apply(region, message)
    owners["held"].apply_held(returned[:8])
    for region, message in returned[8:]:
        owners["held"].apply(region, message)
    assert owners["one by one"].dropped > 0 and owners["held"].dropped == owners["in order"].dropped == 0
    now_ms = max(m["newest_data_ms"] for _, m in messages)
    for region in owners["in order"].held:
        assert_same_cells(
            owners["held"].region(region).friction_map.cells(now_ms),
            owners["in order"].region(region).friction_map.cells(now_ms),
        )
    for owner in owners.values():
        owner.storage.close()
