"""PostgreSQL's hot path stores by COPY (roadgrip/cloud/storage/telemetry.py `_copy_new`): what it stores must be what
the INSERT path stores, value for value, and a repeat must fall back to the INSERT path with the same counts."""

import random

import pytest

from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.storage.local_postgres import create_database, drop_database
from roadgrip.data.schema import TELEMETRY

T0_MS = 1_767_225_600_000


def awkward_rows(n: int, seed: int) -> tuple[list[dict], list[dict]]:
    """Telemetry and estimates whose floats need all 17 digits (random doubles, 1/3, the smallest normal double),
    with nulls in the optional columns and both booleans."""
    rng = random.Random(seed)
    extremes = [1 / 3, 2.2250738585072014e-308, -1e-300, 0.1 + 0.2, 123456.789e-3]
    telemetry, estimates = [], []
    for i in range(n):
        row = {}
        for k, c in enumerate(TELEMETRY):
            if c.name in ("vehicle_id", "timestamp_ms"):
                continue
            if str(c.type) == "bool":
                row[c.name] = None if not c.required and i % 3 == 0 else bool((i + k) % 2)
            elif not c.required and (i + k) % 4 == 0:
                row[c.name] = None
            else:
                row[c.name] = (
                    extremes[(i + k) % len(extremes)] if i % 2 else rng.uniform(-1, 1) * 10 ** rng.randint(-8, 4)
                )
        vehicle = f"car-{i % 3}.x_{seed}"
        telemetry.append({"vehicle_id": vehicle, "timestamp_ms": T0_MS + 100 * i, **row})
        estimates.append(
            {
                "vehicle_id": vehicle,
                "timestamp_ms": T0_MS + 100 * i,
                "mu": rng.random(),
                "mu_lower": rng.random() / 3,
                "mu_upper": 1 / 3 + rng.random(),
                "excited": i % 2 == 0,
                "estimator": "pmf",
                "mu_proven": None if i % 5 == 0 else rng.random() / 7,
                "latitude_deg": None if i % 4 == 0 else 48 + rng.random(),
                "longitude_deg": None if i % 4 == 0 else 11 + rng.random(),
                "h3_cell": None if i % 4 == 0 else "8a1f8d2a1b27fff",
            }
        )
    return telemetry, estimates


@pytest.fixture
def two_postgres(postgres_url):
    """Two fresh databases on the session's server: one written by COPY, one by INSERT."""
    names = [f"copy_{random.getrandbits(48):012x}", f"insert_{random.getrandbits(48):012x}"]
    stores = [open_storage(create_database(postgres_url, name)) for name in names]
    stores[1]._telemetry.use_copy = False
    yield stores
    for store in stores:
        store.close()
    for name in names:
        drop_database(postgres_url, name)


def stored(storage) -> tuple[list[dict], list[dict]]:
    rows = [], []
    for vehicle in sorted(storage.telemetry_extent()):
        rows[0].extend(storage.telemetry(vehicle))
        rows[1].extend(storage.estimates(vehicle))
    return rows


def test_copy_stores_what_insert_stores(two_postgres):
    by_copy, by_insert = two_postgres
    assert by_copy._telemetry.use_copy and not by_insert._telemetry.use_copy
    telemetry, estimates = awkward_rows(300, seed=1)
    for store in two_postgres:
        written = store.write_batch(telemetry, estimates)
        assert (written.telemetry, written.estimates, written.already_stored) == (300, 300, frozenset())
    copied = stored(by_copy)
    assert copied == stored(by_insert)
    # and what was sent, value for value (every float exactly)
    assert sorted(copied[0], key=lambda r: r["timestamp_ms"]) == telemetry
    assert sorted(copied[1], key=lambda r: r["timestamp_ms"]) == estimates


def test_a_repeat_under_copy_falls_back_with_the_insert_paths_counts(two_postgres):
    telemetry, estimates = awkward_rows(40, seed=2)
    results = []
    for store in two_postgres:
        store.write_batch(telemetry[:25], estimates[:25])
        results.append(store.write_batch(telemetry + telemetry[:3], estimates))  # 25 stored before, 3 twice here
    assert results[0] == results[1]
    assert (results[0].telemetry, results[0].estimates) == (15, 15)
    assert results[0].already_stored == frozenset((r["vehicle_id"], r["timestamp_ms"]) for r in telemetry[:25])
    assert stored(two_postgres[0]) == stored(two_postgres[1])
