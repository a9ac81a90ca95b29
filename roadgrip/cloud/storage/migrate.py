"""Bringing a database to the schema of storage/schema.py: the Alembic migrations in storage/migrations/ (env.py,
versions/; shipped as package data), run by `open_storage` through `upgrade`, with a Config built here (no
alembic.ini). The version is kept in the table VERSION_TABLE.

- The first revision creates the tables a database lacks, as they are today: all of them for a new database; for one
  made by a roadgrip from before the migrations (which has no VERSION_TABLE), those that came after it (such as
  estimator_states). The later ones do what open_storage did by hand before: estimates.mu_proven added (older rows
  hold null there), the credentials' role check widened to the station role. Upgrades only: roadgrip never
  downgrades a database.
- One process at a time: on PostgreSQL under a session advisory lock (processes opening a new database at once, the
  cluster's workers, API replicas and ingest processes starting together, raced in CREATE TABLE and CREATE EXTENSION,
  and all but one failed on a duplicate key of PostgreSQL's catalog); on SQLite in a BEGIN IMMEDIATE transaction,
  which holds the database's write lock. Either way the whole upgrade is one transaction.
- PostGIS is not a revision but a step of every open, as the server allows: with the extension available, estimates
  get a generated column `geom geometry(Point,4326)` (null where the position is) with a GiST index, for spatial
  queries by other tools; a database first made without PostGIS gains it once PostGIS is there.

A new schema change: the table in schema.py, and a revision in versions/ whose down_revision is the newest one
(tests/cloud/storage/test_migrations.py checks that the upgraded database matches schema.py).
"""

from __future__ import annotations

import logging
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from alembic import command
from alembic.config import Config
from sqlalchemy import exc, text
from sqlalchemy.engine import Connection, Engine

from roadgrip.cloud.storage.base import reported

log = logging.getLogger(__name__)

MIGRATIONS = Path(__file__).with_name("migrations")  # Alembic's script location
VERSION_TABLE = "roadgrip_schema_version"
SCHEMA_LOCK_KEY = 0x726F6164  # "road": the PostgreSQL advisory lock held while the schema is made
POSTGIS_DDL = (
    (
        "ALTER TABLE estimates ADD COLUMN IF NOT EXISTS geom geometry(Point, 4326) "
        "GENERATED ALWAYS AS (ST_SetSRID(ST_MakePoint(longitude_deg, latitude_deg), 4326)) STORED"
    ),
    "CREATE INDEX IF NOT EXISTS ix_estimates_geom ON estimates USING GIST (geom)",
)
POSTGIS_OBJECTS = frozenset({"geom", "ix_estimates_geom", "spatial_ref_sys"})  # POSTGIS_DDL's and the extension's


def not_postgis(obj, name, type_, reflected, compare_to) -> bool:
    """Alembic's include_object for comparing a database with schema.py (autogenerate): all but POSTGIS_OBJECTS."""
    return name not in POSTGIS_OBJECTS


def alembic_config(connection: Connection) -> Config:
    """Alembic's configuration for migrating the database of `connection` (migrations/env.py takes it from
    `attributes`)."""
    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.attributes["connection"] = connection
    return config


@contextmanager
def _schema_lock(engine: Engine) -> Iterator[None]:
    """On PostgreSQL, a session advisory lock held while the schema is made (see the module's docstring)."""
    if engine.dialect.name != "postgresql":
        yield
        return
    with engine.connect() as conn:
        conn.execute(text(f"SELECT pg_advisory_lock({SCHEMA_LOCK_KEY})"))
        try:
            yield
        finally:
            conn.execute(text(f"SELECT pg_advisory_unlock({SCHEMA_LOCK_KEY})"))


def _enable_postgis(engine: Engine, where: str) -> bool:
    """Try to create the PostGIS extension; False (and a log line) where the server lacks it or forbids it."""
    with engine.connect() as conn:  # a server that cannot be reached fails here, not as "no PostGIS"
        try:
            with conn.begin():
                conn.execute(text("CREATE EXTENSION IF NOT EXISTS postgis"))
            return True
        except exc.DBAPIError as err:
            if err.connection_invalidated:
                raise
            log.warning("PostGIS not available on %s, estimates get no geom column: %s", where, err.orig)
            return False


def upgrade(engine: Engine) -> bool:
    """Bring the database of `engine` to the newest revision (and PostGIS's geom column where PostGIS is available);
    whether PostGIS is there. StorageUnavailable where the database cannot be reached."""
    where = engine.url.render_as_string(hide_password=True)
    with reported(where), _schema_lock(engine):
        postgis = engine.dialect.name == "postgresql" and _enable_postgis(engine, where)
        with engine.begin() as conn:
            if engine.dialect.name == "sqlite":
                # pysqlite leaves DDL outside transactions: this one holds the write lock from the start
                conn.exec_driver_sql("BEGIN IMMEDIATE")
            command.upgrade(alembic_config(conn), "head")
            for statement in POSTGIS_DDL if postgis else ():
                conn.execute(text(statement))
    return postgis
