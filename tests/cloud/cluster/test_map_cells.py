"""The friction map saved to the database and read back (cluster mode): the same cell summaries at any later `now` as the
map that saved them, on SQLite and PostgreSQL; a region's cells restored alone; writes fenced by a region queue's
epoch."""

from __future__ import annotations

import dataclasses

import h3
import numpy as np
import pytest

from roadgrip.cloud.cluster.map_cells import cell_rows, new_friction_map, region_of, restore_region, stored_friction_map
from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.formats.geojson import geojson
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Fenced, counters_table

T0_MS = 1_768_464_000_000
REGION_RESOLUTION = 5
HEBEI = (38.0, 114.5)
FAR = (48.1, 11.5)  # another region


def estimates(vehicle: str, start_ms: int, origin: tuple[float, float], n: int, mu: float, seed: int) -> list[dict]:
    """A vehicle driving east at 20 m/s, 10 Hz, through several cells; excited every third sample."""
    rng = np.random.default_rng(seed)
    rows = []
    for k in range(n):
        spread = rng.uniform(0.05, 0.2)
        rows.append(
            {
                "vehicle_id": vehicle,
                "timestamp_ms": start_ms + 100 * k,
                "latitude_deg": origin[0],
                "longitude_deg": origin[1] + 2.0 / 111_000 * k * 1.27,
                "mu": mu,
                "mu_lower": mu - spread,
                "mu_upper": mu + spread,
                "excited": k % 3 == 0,
                "mu_proven": 0.3 if k % 7 == 0 else None,
            }
        )
    return rows


def a_map(settings: Settings) -> FrictionMap:
    fmap = new_friction_map(settings)
    fmap.add(estimates("v1", T0_MS, HEBEI, 300, 0.2, 1), T0_MS + 30_000)
    fmap.add(estimates("v2", T0_MS + 40_000, HEBEI, 300, 0.8, 2), T0_MS + 70_000)  # v1's last pass closes later
    fmap.add(estimates("v3", T0_MS + 60_000, FAR, 200, 0.5, 3), T0_MS + 80_000)
    station_cell = h3.latlng_to_cell(*HEBEI, settings.h3_resolution)
    fmap.add_station(
        [
            {
                "station_id": "s1",
                "cell": station_cell,
                "timestamp_ms": T0_MS + 50_000,
                "mu": 0.3,
                "mu_lower": 0.2,
                "mu_upper": 0.4,
            }
        ],
        T0_MS + 80_000,
    )
    return fmap


@pytest.mark.parametrize("later_s", [0, 90, 1800, 3500, 4000])
def test_a_map_read_back_from_storage_says_what_the_saved_one_says_at_any_later_now(storage, later_s):
    settings = Settings()
    fmap = a_map(settings)
    assert fmap.open_passes_, "the test needs passes in progress"
    storage.put_region_output([], cell_rows(fmap, fmap.cells_by_id_, REGION_RESOLUTION))
    now_ms = T0_MS + 80_000 + later_s * 1000
    read = stored_friction_map(storage, settings, now_ms)
    assert read.cells(now_ms) == fmap.cells(now_ms)
    assert geojson(read.cells(now_ms)) == geojson(fmap.cells(now_ms))


def test_a_saved_pass_in_progress_that_moved_on_counts_as_the_saving_map_folded_it(storage):
    settings = Settings()
    fmap = new_friction_map(settings)
    first = fmap.add(estimates("v1", T0_MS, HEBEI, 30, 0.2, 1), T0_MS + 3_000)  # its pass in progress in the last
    storage.put_region_output([], cell_rows(fmap, first, REGION_RESOLUTION))
    moved = estimates("v1", T0_MS + 3_000, HEBEI, 300, 0.2, 1)[100:]  # now in other cells
    touched = fmap.add(moved, T0_MS + 30_000)
    assert not first & touched
    storage.put_region_output([], cell_rows(fmap, touched, REGION_RESOLUTION))  # the first cells not saved again
    now_ms = T0_MS + 40_000
    read = stored_friction_map(storage, settings, now_ms)
    for got, want in zip(read.cells(now_ms), fmap.cells(now_ms), strict=True):
        for name, value in dataclasses.asdict(want).items():  # folded here, summed in another order there
            assert getattr(got, name) == (pytest.approx(value, rel=1e-12) if isinstance(value, float) else value)


def test_a_region_is_restored_alone_and_writes_of_a_region_queue_taken_since_are_fenced(storage):
    settings = Settings()
    fmap = a_map(settings)
    rows = cell_rows(fmap, fmap.cells_by_id_, REGION_RESOLUTION)
    hebei = region_of(h3.latlng_to_cell(*HEBEI, settings.h3_resolution), REGION_RESOLUTION)
    assert {row["region"] for row in rows} == {hebei, region_of(h3.latlng_to_cell(*FAR, 10), REGION_RESOLUTION)}
    old = storage.take_region_queue(2, "a")
    storage.put_region_output([], rows, fence=(2, old))
    new = storage.take_region_queue(2, "b")
    assert new == old + 1
    with pytest.raises(Fenced):
        storage.put_region_output([], rows[:1], fence=(2, old))
    restored = new_friction_map(settings)
    assert restore_region(restored, storage, hebei) == sum(row["region"] == hebei for row in rows)
    now_ms = T0_MS + 100_000
    assert restored.cells(now_ms) == [c for c in fmap.cells(now_ms) if region_of(c.cell, REGION_RESOLUTION) == hebei]
    assert storage.delete_map_cells(hebei, T0_MS + 10**9, fence=(2, new)) == len(restored.cells_by_id_)
    assert storage.map_cells(region=hebei) == []


def test_the_clusters_denm_action_ids_are_counted_in_the_database_and_wrap_at_65536(storage):
    assert [storage.next_action_sequence_number() for _ in range(3)] == [0, 1, 2]
    with storage._transaction() as conn:  # near the end of the 16-bit range
        conn.execute(counters_table.update().values(value=65534))
    assert [storage.next_action_sequence_number() for _ in range(3)] == [65535, 0, 1]
