"""The schema's migrations (roadgrip/cloud/storage/migrate.py, migrations/): a new database is at the newest revision
and matches schema.py; a database made by a roadgrip from before the migrations is upgraded and keeps its rows;
processes opening one database at once all succeed."""

import multiprocessing as mp
import warnings

import pytest
import sqlalchemy as sa
from alembic.autogenerate import compare_metadata
from alembic.runtime.migration import MigrationContext
from alembic.script import ScriptDirectory
from sqlalchemy import Column, Table

from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.storage.engine import normalise_url
from roadgrip.cloud.storage.migrate import VERSION_TABLE, alembic_config, not_postgis
from roadgrip.cloud.storage.schema import metadata, telemetry_table, vehicles_table, warnings_table
from roadgrip.data.schema import CHANNEL_NAMES
from tests.cloud.storage.test_storage import T0_MS, counted, drive, estimate_row, telemetry_row

HEAD = ScriptDirectory.from_config(alembic_config(None)).get_current_head()


def database_revision(url: str) -> str | None:
    engine = sa.create_engine(normalise_url(url))
    try:
        with engine.connect() as conn:
            return MigrationContext.configure(conn, opts={"version_table": VERSION_TABLE}).get_current_revision()
    finally:
        engine.dispose()


def schema_differences(url: str) -> list:
    """What Alembic's autogenerate finds between the database and schema.py (PostGIS's objects left out)."""
    engine = sa.create_engine(normalise_url(url))
    try:
        with engine.connect() as conn, warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="Did not recognize type 'geometry'")
            context = MigrationContext.configure(
                conn, opts={"version_table": VERSION_TABLE, "compare_type": True, "include_object": not_postgis}
            )
            return compare_metadata(context, metadata)
    finally:
        engine.dispose()


def test_a_new_database_is_at_the_newest_revision_and_matches_the_schema(storage_url):
    assert database_revision(storage_url) is None
    open_storage(storage_url).close()
    assert HEAD == "0005_observations" and database_revision(storage_url) == HEAD
    assert schema_differences(storage_url) == []
    storage = open_storage(storage_url)  # at the newest revision already: nothing to do
    assert storage.counts()["telemetry"] == 0
    storage.close()


def make_old_database(url: str) -> None:
    """The tables as a roadgrip from before stations, estimator states and the cluster made them (create_all, no
    version table): estimates without mu_proven, credentials whose role check names vehicle, reader and admin; a few
    rows in each."""
    old = sa.MetaData()
    for table in (vehicles_table, warnings_table):
        table.to_metadata(old)
    Table(  # without the optional channels
        "telemetry",
        old,
        *(c.copy() for c in telemetry_table.columns if c.name not in CHANNEL_NAMES),
        sa.PrimaryKeyConstraint("vehicle_id", "timestamp_ms"),
    )
    estimates = Table(
        "estimates",
        old,
        Column("vehicle_id", sa.String, nullable=False),
        Column("timestamp_ms", sa.BigInteger, nullable=False),
        *(Column(name, sa.Float, nullable=False) for name in ("mu", "mu_lower", "mu_upper")),
        Column("excited", sa.Boolean, nullable=False),
        Column("estimator", sa.String, nullable=False),
        Column("latitude_deg", sa.Float),
        Column("longitude_deg", sa.Float),
        Column("h3_cell", sa.String),
        sa.PrimaryKeyConstraint("vehicle_id", "timestamp_ms"),
        sa.Index("ix_estimates_timestamp_ms", "timestamp_ms"),
    )
    credentials = Table(
        "credentials",
        old,
        Column("name", sa.String, primary_key=True),
        Column(
            "role",
            sa.String,
            sa.CheckConstraint("role IN ('vehicle', 'reader', 'admin')", name="ck_credentials_role"),
            nullable=False,
        ),
        Column("secret_hash", sa.String, nullable=False),
        Column("vehicle_id", sa.String),
        Column("revoked", sa.Boolean, nullable=False),
        Column("created_ms", sa.BigInteger, nullable=False),
    )
    engine = sa.create_engine(normalise_url(url))
    try:
        with engine.begin() as conn:
            old.create_all(conn)
            old_rows = [telemetry_row("car-1", T0_MS + 100 * i) for i in range(3)]
            conn.execute(
                old.tables["telemetry"].insert(),
                [{k: v for k, v in r.items() if k not in CHANNEL_NAMES} for r in old_rows],
            )
            conn.execute(
                estimates.insert(),
                [
                    {k: v for k, v in estimate_row("car-1", T0_MS + 100 * i).items() if k != "mu_proven"}
                    for i in range(3)
                ],
            )
            conn.execute(
                credentials.insert(),
                [
                    {
                        "name": "car-1",
                        "role": "vehicle",
                        "secret_hash": "h1",
                        "vehicle_id": "car-1",
                        "revoked": False,
                        "created_ms": T0_MS,
                    },
                    {
                        "name": "ops",
                        "role": "admin",
                        "secret_hash": "h2",
                        "vehicle_id": None,
                        "revoked": True,
                        "created_ms": T0_MS + 1,
                    },
                ],
            )
            conn.execute(
                old.tables["vehicles"].insert().values(vehicle_id="car-1", profile={"mass_kg": 1500}, updated_ms=T0_MS)
            )
            with pytest.raises(sa.exc.IntegrityError), conn.begin_nested():  # the old check, as it was
                conn.execute(
                    credentials.insert().values(
                        name="rsu-1", role="station", secret_hash="h", revoked=False, created_ms=T0_MS
                    )
                )
    finally:
        engine.dispose()


def test_a_database_of_an_older_roadgrip_is_upgraded_and_keeps_its_rows(storage_url):
    make_old_database(storage_url)
    assert database_revision(storage_url) is None
    storage = open_storage(storage_url)
    try:
        assert database_revision(storage_url) == HEAD
        assert storage.counts() == {"telemetry": 3, "estimates": 3, "vehicles": 1, "warnings": 0}
        assert [r["mu_proven"] for r in storage.estimates("car-1")] == [None, None, None]
        assert [r["mu"] for r in storage.estimates("car-1")] == [0.8] * 3
        with storage._transaction() as conn:  # the optional channels added, null (not sent) in the old rows
            old_channels = conn.execute(sa.text(f"SELECT {', '.join(CHANNEL_NAMES)} FROM telemetry")).all()
        assert [tuple(r) for r in old_channels] == [(None,) * len(CHANNEL_NAMES)] * 3
        assert [(c.name, c.role, c.secret_hash, c.revoked) for c in storage.credentials()] == [
            ("car-1", "vehicle", "h1", False),
            ("ops", "admin", "h2", True),
        ]
        assert storage.vehicle_profile("car-1") == {"mass_kg": 1500}
        storage.add_credential("rsu-1", "station", "h3")  # the widened check
        with pytest.raises(ValueError, match="rejected by database"), storage._transaction() as conn:  # still a check
            conn.execute(sa.text("UPDATE credentials SET role = 'superuser' WHERE name = 'rsu-1'"))
        written = storage.write_batch(
            [telemetry_row("car-1", T0_MS + 1000)], [estimate_row("car-1", T0_MS + 1000, mu_proven=0.42)]
        )
        assert counted(written) == (1, 1) and storage.estimates("car-1")[-1]["mu_proven"] == 0.42
        storage.put_estimator_states([{"vehicle_id": "car-1", "estimator": "pmf", "state": {"a": 1}}])  # a new table
        assert storage.take_partition(0, "worker-1") == 1 and storage.next_action_sequence_number() == 0
    finally:
        storage.close()
    assert schema_differences(storage_url) == []


def open_and_write(url: str, index: int, barrier) -> None:
    barrier.wait()
    storage = open_storage(url)
    try:
        storage.write_batch(*drive(f"car-{index}", 5))
    finally:
        storage.close()


def test_processes_opening_a_new_database_at_once_all_succeed(storage_url):
    """Four processes open the same new database at the same moment: each one's open waits for the one making the
    schema (PostgreSQL: the advisory lock; SQLite: the write lock), and finds it made."""
    context = mp.get_context("spawn")
    barrier = context.Barrier(4)
    processes = [context.Process(target=open_and_write, args=(storage_url, i, barrier)) for i in range(4)]
    for process in processes:
        process.start()
    for process in processes:
        process.join(120)
    assert [p.exitcode for p in processes] == [0, 0, 0, 0]
    assert database_revision(storage_url) == HEAD
    storage = open_storage(storage_url)
    assert storage.counts()["telemetry"] == 20
    storage.close()
