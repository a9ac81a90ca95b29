"""Storage URLs and engines: `normalise_url` (the drivers roadgrip supports, made explicit) and `make_engine`, an
SQLAlchemy engine set up for roadgrip's use of each database (SQLite: WAL journal, synchronous=NORMAL, foreign keys
on, a busy timeout; PostgreSQL through psycopg 3: a connect timeout and positional parameters passed through)."""

from __future__ import annotations

import sqlite3
import time
from pathlib import Path

import psycopg
import sqlalchemy as sa
from sqlalchemy import exc
from sqlalchemy.engine import URL, Engine, make_url

from roadgrip.cloud.storage.base import StorageUnavailable

SQLITE_BUSY_TIMEOUT_MS = 10_000  # how long a writer waits for another one's lock before giving up
WAL_RETRY_S = 0.05  # switching to WAL found the database locked: asked again this often, within the busy timeout
CONNECT_TIMEOUT_S = 5  # PostgreSQL: how long to wait for the server before calling it unavailable


def normalise_url(url: str) -> URL:
    """`url` with its driver made explicit (sqlite+pysqlite, postgresql+psycopg); ValueError if it is not supported."""
    try:
        sa_url = make_url(url)
    except exc.ArgumentError:
        raise ValueError(
            f"storage URL {url.partition('://')[0]}://... is not a database URL: "
            "use sqlite:///PATH or postgresql://USER@HOST:PORT/DATABASE"
        ) from None
    backend, _, driver = sa_url.drivername.partition("+")
    if backend in ("postgresql", "postgres") and driver in ("", "psycopg"):
        return sa_url.set(drivername="postgresql+psycopg")
    if backend == "sqlite" and driver in ("", "pysqlite"):
        if sa_url.database in (None, "", ":memory:"):
            raise ValueError(f"storage URL {url!r}: SQLite storage needs a file, sqlite:///PATH")
        return sa_url.set(drivername="sqlite+pysqlite")
    raise ValueError(
        f"unsupported storage URL scheme {sa_url.drivername!r}: "
        "use sqlite:///PATH or postgresql://USER@HOST:PORT/DATABASE"
    )


def _sqlite_pragmas(dbapi_connection, connection_record) -> None:
    cursor = dbapi_connection.cursor()
    # busy_timeout first: switching a new database to WAL takes its lock, and a process that finds another one
    # switching it would otherwise fail at once ("database is locked") instead of waiting
    cursor.execute(f"PRAGMA busy_timeout={SQLITE_BUSY_TIMEOUT_MS}")
    _switch_to_wal(cursor)
    cursor.execute("PRAGMA synchronous=NORMAL")
    cursor.execute("PRAGMA foreign_keys=ON")
    cursor.close()


def _switch_to_wal(cursor) -> None:
    """journal_mode=WAL, asked again while the database is locked: SQLite does not always call the busy handler for
    the exclusive lock this switch takes (processes opening a new database at once), so busy_timeout alone does not
    cover it. WAL is kept in the file: once one process has switched, the others only read it."""
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_MS / 1000.0
    while True:
        try:
            cursor.execute("PRAGMA journal_mode=WAL")
            return
        except sqlite3.OperationalError as err:
            if "locked" not in str(err) or time.monotonic() >= deadline:
                raise
            time.sleep(WAL_RETRY_S)


def make_engine(sa_url: URL) -> Engine:
    """The engine of a URL from `normalise_url`; the parent folder of an SQLite file is created (StorageUnavailable
    if it cannot be). Connects to nothing yet."""
    if sa_url.get_backend_name() == "sqlite":
        try:
            Path(sa_url.database).parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StorageUnavailable(
                f"database {sa_url.render_as_string(hide_password=True)} unavailable: {err}"
            ) from err
        engine = sa.create_engine(sa_url)
        sa.event.listen(engine, "connect", _sqlite_pragmas)
        return engine
    # Positional $n parameters passed through as they are (psycopg's RawCursor): psycopg's conversion of named
    # parameters is slow for a multi-row INSERT (17 parameters a row) and cut the write rate to a quarter.
    return sa.create_engine(
        sa_url,
        pool_pre_ping=True,
        paramstyle="numeric_dollar",
        connect_args={"connect_timeout": CONNECT_TIMEOUT_S, "cursor_factory": psycopg.RawCursor},
    )
