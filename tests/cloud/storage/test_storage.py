import contextlib
import socket
import threading

import psycopg
import pytest
from sqlalchemy import text
from sqlalchemy.engine import make_url

from roadgrip.cloud.storage.database import Credential, StorageUnavailable, Written, open_storage
from roadgrip.data.schema import TELEMETRY

T0_MS = 1_767_225_600_000  # 2026-01-01T00:00:00Z
INJECTION = "x'); DROP TABLE telemetry;--"


def telemetry_row(vehicle_id="car-1", timestamp_ms=T0_MS, **values):
    row = {c.name: 0.5 for c in TELEMETRY}
    row.update(
        vehicle_id=vehicle_id,
        timestamp_ms=timestamp_ms,
        latitude_deg=48.1,
        longitude_deg=11.5,
        abs_active=False,
        acc_active=True,
        tcs_active=None,
        esc_active=False,
        lateral_speed_mps=None,
    )
    row.update(values)
    return row


def estimate_row(vehicle_id="car-1", timestamp_ms=T0_MS, **values):
    row = {
        "vehicle_id": vehicle_id,
        "timestamp_ms": timestamp_ms,
        "mu": 0.8,
        "mu_lower": 0.6,
        "mu_upper": 0.95,
        "excited": True,
        "estimator": "sa-cnn-lstm",
        "mu_proven": 0.3,
        "latitude_deg": 48.1,
        "longitude_deg": 11.5,
        "h3_cell": "8a1f8d2a1b27fff",
    }
    row.update(values)
    return row


def drive(vehicle_id, n, t0_ms=T0_MS):
    """n telemetry rows and n estimates of one vehicle, 100 ms apart."""
    times = [t0_ms + 100 * i for i in range(n)]
    return [telemetry_row(vehicle_id, t) for t in times], [
        estimate_row(vehicle_id, t, mu=0.1 + i / n) for i, t in enumerate(times)
    ]


@contextlib.contextmanager
def closed_port():
    """A port on 127.0.0.1 on which nothing listens: bound but not listening, while the context lasts."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def counted(written: Written) -> tuple[int, int]:
    return written.telemetry, written.estimates


# -------------------------------------------------------------------------------------------- opening


def test_opening_twice_keeps_the_schema_and_the_rows(storage_url):
    first = open_storage(storage_url)
    assert counted(first.write_batch(*drive("car-1", 10))) == (10, 10)
    first.close()
    second = open_storage(storage_url)
    assert second.dialect == make_url(storage_url).get_backend_name()
    assert second.counts() == {"telemetry": 10, "estimates": 10, "vehicles": 0, "warnings": 0}
    second.ping()
    second.close()


def test_sqlite_connections_use_wal_normal_sync_foreign_keys_and_a_busy_timeout(tmp_path):
    storage = open_storage(f"sqlite:///{tmp_path / 'nested' / 'roadgrip.db'}")
    with storage._engine.connect() as conn:
        pragma = {
            name: conn.execute(text(f"PRAGMA {name}")).scalar()
            for name in ("journal_mode", "synchronous", "foreign_keys", "busy_timeout")
        }
    storage.close()
    assert pragma == {"journal_mode": "wal", "synchronous": 1, "foreign_keys": 1, "busy_timeout": 10_000}


def test_unsupported_urls_are_named(tmp_path):
    with pytest.raises(ValueError, match="'mysql\\+pymysql'"):
        open_storage("mysql+pymysql://user:pw@localhost/roadgrip")
    with pytest.raises(ValueError, match="'postgresql\\+psycopg2'"):
        open_storage("postgresql+psycopg2://user@localhost/roadgrip")
    with pytest.raises(ValueError, match="needs a file"):
        open_storage("sqlite://")
    with pytest.raises(ValueError, match="not a database URL"):
        open_storage(str(tmp_path / "roadgrip.db"))


def test_plain_postgresql_urls_use_psycopg_and_hide_the_password(postgres_database_url):
    url = make_url(postgres_database_url).set(drivername="postgresql", password="s3cret")
    given = url.render_as_string(hide_password=False)
    storage = open_storage(given)  # the test server trusts 127.0.0.1: the password is not checked
    assert storage.url == given and storage.dialect == "postgresql"
    assert "s3cret" not in repr(storage) and "s3cret" not in str(storage)
    storage.close()


def test_a_closed_port_or_a_file_in_the_way_raises_storage_unavailable(tmp_path):
    with closed_port() as port, pytest.raises(StorageUnavailable, match=f"127.0.0.1:{port}") as err:
        open_storage(f"postgresql://postgres:s3cret@127.0.0.1:{port}/roadgrip")
    assert "s3cret" not in str(err.value)
    (tmp_path / "a-file").write_text("")
    with pytest.raises(StorageUnavailable, match="a-file"):
        open_storage(f"sqlite:///{tmp_path / 'a-file' / 'roadgrip.db'}")


def test_ping_raises_storage_unavailable_once_the_server_refuses(postgres_url, postgres_database_url):
    storage = open_storage(postgres_database_url)
    storage.ping()
    name = make_url(postgres_database_url).database
    with psycopg.connect(
        make_url(postgres_url).set(drivername="postgresql").render_as_string(False), autocommit=True
    ) as admin:
        admin.execute(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS false')
        admin.execute("SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = %s", (name,))
        with pytest.raises(StorageUnavailable, match="not currently accepting connections"):
            storage.ping()
        admin.execute(f'ALTER DATABASE "{name}" ALLOW_CONNECTIONS true')
    storage.ping()  # and it comes back by itself
    storage.close()


# -------------------------------------------------------------------------------------------- telemetry and estimates


def test_write_batch_counts_new_rows_and_skips_duplicates(storage):
    telemetry, estimates = drive("car-1", 2500)  # past one 1,000-row INSERT
    duplicated = telemetry[:1200] + telemetry[1000:1100]  # repeats within one batch
    assert counted(storage.write_batch(duplicated, estimates[:1200] + estimates[:5])) == (1200, 1200)
    assert counted(storage.write_batch(telemetry, estimates)) == (1300, 1300)  # overlaps the first batch
    assert counted(storage.write_batch(telemetry, estimates)) == (0, 0)
    assert counted(storage.write_batch([], [])) == (0, 0)
    again = telemetry_row(timestamp_ms=T0_MS - 100)
    one_insert = storage.write_batch([again, again], [estimate_row(timestamp_ms=T0_MS - 100)] * 2)
    assert counted(one_insert) == (1, 1)
    assert storage.counts() == {"telemetry": 2501, "estimates": 2501, "vehicles": 0, "warnings": 0}


def test_write_batch_names_the_telemetry_rows_stored_before(storage):
    telemetry, estimates = drive("car-1", 600)
    assert storage.write_batch(telemetry[100:300], estimates[100:300]).already_stored == frozenset()
    other = telemetry_row("car-2", T0_MS + 100)
    written = storage.write_batch(telemetry + [other, other], estimates)  # the second try: RETURNING
    assert written.already_stored == {("car-1", r["timestamp_ms"]) for r in telemetry[100:300]}
    assert counted(written) == (401, 400)
    assert storage.counts()["telemetry"] == 601


def test_rows_come_back_as_written(storage):
    row = telemetry_row(lateral_speed_mps=-0.25, abs_active=True, speed_mps=27.5)
    sparse = telemetry_row(timestamp_ms=T0_MS + 100)
    for optional in ("latitude_deg", "longitude_deg", "lateral_speed_mps"):
        del sparse[optional]  # absent means null
    estimate = estimate_row(latitude_deg=None, longitude_deg=None, h3_cell=None, excited=False)
    assert counted(storage.write_batch([row, sparse], [estimate])) == (2, 1)
    assert storage.telemetry("car-1") == [
        row,
        {**sparse, "latitude_deg": None, "longitude_deg": None, "lateral_speed_mps": None},
    ]
    assert storage.estimates("car-1") == [estimate]


def test_a_failing_batch_stores_nothing(storage):
    telemetry, estimates = drive("car-1", 3)
    with pytest.raises(ValueError, match="mu"):
        storage.write_batch(telemetry, estimates[:2] + [estimate_row(timestamp_ms=T0_MS + 200, mu=None)])
    assert storage.counts()["telemetry"] == 0


def test_unknown_or_missing_keys_are_named(storage):
    with pytest.raises(ValueError, match=r"telemetry row 1: unknown keys \['speed_kmh'\]"):
        storage.write_batch([telemetry_row(), telemetry_row(speed_kmh=90.0)], [])
    without_speed = telemetry_row()
    del without_speed["speed_mps"]
    with pytest.raises(ValueError, match=r"telemetry row 0: missing required keys \['speed_mps'\]"):
        storage.write_batch([without_speed], [])
    with pytest.raises(ValueError, match=r"estimate row 0: missing required keys \['mu_upper'\]"):
        storage.write_batch([], [{k: v for k, v in estimate_row().items() if k != "mu_upper"}])


def test_range_queries_are_half_open_ordered_and_per_vehicle(storage):
    storage.write_batch(*drive("car-1", 50))
    storage.write_batch(*drive("car-2", 20, t0_ms=T0_MS + 50))
    times = [e["timestamp_ms"] for e in storage.estimates("car-1", T0_MS + 1000, T0_MS + 2000)]
    assert times == [T0_MS + 100 * i for i in range(10, 20)]
    assert [e["timestamp_ms"] for e in storage.estimates("car-1", end_ms=T0_MS + 300)] == [
        T0_MS,
        T0_MS + 100,
        T0_MS + 200,
    ]
    assert len(storage.estimates("car-1", start_ms=T0_MS + 4500)) == 5
    assert len(storage.estimates("car-1", limit=7)) == 7
    assert len(storage.telemetry("car-2", T0_MS, T0_MS + 1000)) == 10
    assert storage.estimates("nobody") == [] and storage.telemetry("nobody") == []
    since = storage.estimates_since(T0_MS + 1000)
    assert len(since) == 40 + 10
    assert [e["timestamp_ms"] for e in since] == sorted(e["timestamp_ms"] for e in since)
    assert {e["vehicle_id"] for e in storage.estimates_since(T0_MS, limit=3)} == {"car-1", "car-2"}
    assert storage.latest_timestamps() == {"car-1": T0_MS + 4900, "car-2": T0_MS + 50 + 1900}
    assert storage.telemetry_extent() == {
        "car-1": (50, T0_MS, T0_MS + 4900),
        "car-2": (20, T0_MS + 50, T0_MS + 50 + 1900),
    }
    with pytest.raises(ValueError, match="limit"):
        storage.estimates("car-1", limit=0)


def test_latest_estimates_are_each_vehicles_newest_row(storage):
    for vehicle_id in ("car-1", "car-2", "car-3"):  # car-3 has a profile and no estimate yet
        storage.put_vehicle(vehicle_id, {"mass_kg": 1500.0})
    assert storage.latest_estimates() == []
    storage.write_batch(*drive("car-1", 50))
    storage.write_batch(*drive("car-2", 20, t0_ms=T0_MS + 50))
    no_position = estimate_row("car-2", T0_MS + 9000, latitude_deg=None, longitude_deg=None, h3_cell=None)
    storage.write_batch([], [no_position])
    storage.write_batch([], [estimate_row("car-1", T0_MS - 100, mu=0.05)])  # arrives last, is oldest
    latest = storage.latest_estimates()
    assert latest == [storage.estimates("car-1")[-1], no_position]
    assert latest[0]["timestamp_ms"] == T0_MS + 4900 and latest[0]["latitude_deg"] == 48.1
    storage.write_batch([], [estimate_row("car-9", T0_MS + 10_000)])  # no profile: a vehicle never registered
    assert [row["vehicle_id"] for row in storage.latest_estimates()] == ["car-1", "car-2"]


def test_one_writer_and_several_readers_in_threads(storage):
    errors = []

    def write():
        try:
            for k in range(20):
                storage.write_batch(*drive("car-1", 100, t0_ms=T0_MS + 10_000 * k))
        except Exception as err:  # noqa: BLE001 - reported below
            errors.append(err)

    def read():
        try:
            for _ in range(30):
                storage.counts(), storage.estimates("car-1"), storage.latest_timestamps()
        except Exception as err:  # noqa: BLE001 - reported below
            errors.append(err)

    threads = [threading.Thread(target=write)] + [threading.Thread(target=read) for _ in range(3)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert storage.counts()["estimates"] == 2000


# -------------------------------------------------------------------------------------------- PostGIS


def test_postgis_geom_is_the_estimate_position(postgres_database_url):
    storage = open_storage(postgres_database_url)
    assert storage.postgis
    storage.write_batch(
        [], [estimate_row(), estimate_row(timestamp_ms=T0_MS + 100, latitude_deg=None, longitude_deg=None)]
    )
    with storage._engine.connect() as conn:
        rows = conn.execute(
            text("SELECT ST_X(geom), ST_Y(geom), ST_SRID(geom) FROM estimates ORDER BY timestamp_ms")
        ).all()
    storage.close()
    assert [tuple(r) for r in rows] == [(11.5, 48.1, 4326), (None, None, None)]


def test_without_postgis_everything_else_works(postgres_url, postgres_database_url):
    """A database owner who may not create the extension (not a superuser): no geom column, no failure."""
    name = make_url(postgres_database_url).database
    with psycopg.connect(
        make_url(postgres_url).set(drivername="postgresql").render_as_string(False), autocommit=True
    ) as admin:
        role = f"owner_{name}"
        admin.execute(f'CREATE ROLE "{role}" LOGIN')
        admin.execute(f'ALTER DATABASE "{name}" OWNER TO "{role}"')
    storage = open_storage(make_url(postgres_database_url).set(username=role).render_as_string(False))
    assert not storage.postgis
    assert counted(storage.write_batch(*drive("car-1", 5))) == (5, 5)
    assert len(storage.estimates("car-1")) == 5
    storage.close()


# -------------------------------------------------------------------------------------------- credentials and vehicles


def test_credentials_add_duplicate_revoke_and_rehash(storage):
    storage.add_credential("car-1", "vehicle", "hash-1")
    storage.add_credential("dashboard", "reader", "hash-2")
    car = storage.credential("car-1")
    assert isinstance(car, Credential)
    assert (car.role, car.secret_hash, car.vehicle_id, car.revoked) == ("vehicle", "hash-1", "car-1", False)
    assert car.created_ms > T0_MS
    assert storage.credential("dashboard").vehicle_id is None and storage.credential("nobody") is None
    with pytest.raises(ValueError, match="'car-1' exists"):
        storage.add_credential("car-1", "reader", "other")
    with pytest.raises(ValueError, match="'superuser'"):
        storage.add_credential("root", "superuser", "h")
    with pytest.raises(ValueError, match="vehicle_id"):
        storage.add_credential("car-2", "vehicle", "h", vehicle_id="car-3")
    with pytest.raises(ValueError, match="vehicle_id"):
        storage.add_credential("ops", "admin", "h", vehicle_id="car-1")
    assert storage.revoke_credential("car-1") is True
    assert storage.revoke_credential("car-1") is False
    assert storage.revoke_credential("nobody") is False
    storage.set_secret_hash("dashboard", "hash-3")
    with pytest.raises(ValueError, match="'nobody'"):
        storage.set_secret_hash("nobody", "h")
    assert [(c.name, c.revoked, c.secret_hash) for c in storage.credentials()] == [
        ("car-1", True, "hash-1"),
        ("dashboard", False, "hash-3"),
    ]


def test_a_fleet_is_registered_all_or_nothing(storage):
    storage.register_vehicles([("car-1", {"mass_kg": 1500.0}, "hash-1"), ("car-2", {"mass_kg": 1600.0}, "hash-2")])
    assert storage.vehicle_profile("car-2") == {"mass_kg": 1600.0}
    assert (storage.credential("car-1").role, storage.credential("car-1").secret_hash) == ("vehicle", "hash-1")
    before = storage.counts()
    with pytest.raises(ValueError, match="already registered: car-2"):  # car-3 comes first and is rolled back
        storage.register_vehicles([("car-3", {"mass_kg": 1700.0}, "hash-3"), ("car-2", {"mass_kg": 1.0}, "h")])
    with pytest.raises(ValueError, match="given twice: car-4"):
        storage.register_vehicles([("car-4", {}, "h"), ("car-4", {}, "h")])
    assert storage.credential("car-3") is None and storage.vehicle_profile("car-3") is None
    assert storage.vehicle_profile("car-2") == {"mass_kg": 1600.0} and storage.counts() == before
    assert [c.name for c in storage.credentials()] == ["car-1", "car-2"]


def test_vehicle_profiles_are_upserted(storage):
    profile = {"mass_kg": 2335.0, "wheelbase_m": 3.008, "drive": "awd", "tires": {"radius_m": 0.37}}
    storage.put_vehicle("car-1", profile)
    storage.put_vehicle("car-2", {"mass_kg": 1200.0})
    storage.put_vehicle("car-1", {**profile, "mass_kg": 2400.0})
    assert storage.vehicle_profile("car-1") == {**profile, "mass_kg": 2400.0}
    assert storage.vehicle_profile("nobody") is None
    assert storage.vehicle_ids() == ["car-1", "car-2"]
    assert storage.counts()["vehicles"] == 2
    with pytest.raises(TypeError, match="dict"):
        storage.put_vehicle("car-3", "mass_kg: 1200")


def warning_row(warning_id, cell, status, detection_ms, updated_ms, message):
    return {
        "warning_id": warning_id,
        "cell": cell,
        "status": status,
        "detection_ms": detection_ms,
        "updated_ms": updated_ms,
        "message": message,
    }


def test_warnings_are_upserted_and_filtered_by_status(storage):
    message = {"causeCode": 6, "subCauseCode": 0, "validityDuration_s": 600}
    storage.put_warnings([warning_row("w1", "8a1f8d2a1b27fff", "active", T0_MS, T0_MS, message)])
    storage.put_warnings(
        [
            warning_row("w2", "8a1f8d2a1b2ffff", "active", T0_MS + 10, T0_MS + 10, message),
            warning_row("w1", "8a1f8d2a1b27fff", "active", T0_MS, T0_MS + 30_000, message),
            warning_row("w1", "8a1f8d2a1b27fff", "cancelled", T0_MS, T0_MS + 60_000, {**message, "cancelled": True}),
        ]
    )  # the last of one warning's rows wins
    warnings = storage.warnings()
    assert [(w["warning_id"], w["status"], w["updated_ms"]) for w in warnings] == [
        ("w1", "cancelled", T0_MS + 60_000),
        ("w2", "active", T0_MS + 10),
    ]
    assert warnings[0]["message"] == {**message, "cancelled": True}
    assert [w["warning_id"] for w in storage.warnings(active_only=True)] == ["w2"]
    assert storage.counts()["warnings"] == 2
    with pytest.raises(TypeError, match="message of warning 'w3' must be a dict"):
        storage.put_warnings([warning_row("w3", "8a1f8d2a1b27fff", "active", T0_MS, T0_MS, "text")])


def test_injection_strings_are_stored_as_data(storage):
    storage.add_credential(INJECTION, "reader", INJECTION)
    storage.put_vehicle(INJECTION, {INJECTION: INJECTION})
    storage.write_batch([telemetry_row(INJECTION)], [estimate_row(INJECTION, estimator=INJECTION)])
    storage.put_warnings([warning_row(INJECTION, INJECTION, INJECTION, T0_MS, T0_MS, {"text": INJECTION})])
    assert storage.credential(INJECTION).secret_hash == INJECTION
    assert storage.vehicle_profile(INJECTION) == {INJECTION: INJECTION}
    assert storage.estimates(INJECTION)[0]["estimator"] == INJECTION
    assert storage.warnings()[0]["status"] == INJECTION
    assert storage.counts() == {"telemetry": 1, "estimates": 1, "vehicles": 1, "warnings": 1}
