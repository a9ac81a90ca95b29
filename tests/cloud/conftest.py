"""Fixtures for the cloud platform's tests.

- `postgres_url` (session): a real PostgreSQL 15 server, started once in a temporary directory on 127.0.0.1 at a free port
  and stopped at the end of the session, with an empty database `roadgrip_test`; the URL of that database.
- `postgres_database_url`: a fresh, empty database on that server for one test, dropped after it.
- `storage_url`: parametrized over "sqlite" and "postgresql", so that a test using it runs on both: a fresh SQLite file
  in the test's tmp_path, or `postgres_database_url`.
- `storage`: `roadgrip.cloud.storage.database.open_storage(storage_url)`, closed after the test.

The server needs the Debian packages of `scripts/install_system_deps.sh`; without them the fixture fails (it never skips),
because "passes on SQLite and PostgreSQL" is part of what the tests check.
"""

from __future__ import annotations

import os
import pwd
import shutil
import subprocess
import tempfile
import uuid
from pathlib import Path

import psycopg
import pytest
from sqlalchemy.engine import make_url

from roadgrip.cloud.edge.broker import free_port
from roadgrip.cloud.storage.database import open_storage

PG_BIN = Path("/usr/lib/postgresql/15/bin")


def _admin_conninfo(url: str) -> str:
    """libpq conninfo for the maintenance database `postgres` of the server that `url` points at."""
    u = make_url(url)
    return f"host={u.host} port={u.port} user={u.username} dbname=postgres"


def _create_database(url: str, name: str) -> str:
    """Create database `name` on the server of `url` (a PostgreSQL URL); return the URL of the new database."""
    with psycopg.connect(_admin_conninfo(url), autocommit=True) as conn:
        conn.execute(f'CREATE DATABASE "{name}"')
    return make_url(url).set(database=name).render_as_string(hide_password=False)


def _drop_database(url: str, name: str) -> None:
    with psycopg.connect(_admin_conninfo(url), autocommit=True) as conn:
        conn.execute(f'DROP DATABASE IF EXISTS "{name}" WITH (FORCE)')


@pytest.fixture(scope="session")
def postgres_url():
    """A PostgreSQL 15 server of our own for the session; yields the URL of its empty database `roadgrip_test`."""
    missing = [p.name for p in (PG_BIN / "initdb", PG_BIN / "pg_ctl") if not p.exists()]
    if missing:
        pytest.fail(f"PostgreSQL 15 not installed ({', '.join(missing)} missing in {PG_BIN}): "
                    "run `bash scripts/install_system_deps.sh`", pytrace=False)
    as_postgres: list[str] = []
    root = Path(tempfile.mkdtemp(prefix="roadgrip-pg-"))  # not under pytest's tmp: its parents are private to root
    if os.geteuid() == 0:  # initdb refuses to run as root
        pw = pwd.getpwnam("postgres")
        os.chown(root, pw.pw_uid, pw.pw_gid)
        as_postgres = ["runuser", "-u", "postgres", "--"]

    def pg(*args: str) -> None:
        subprocess.run([*as_postgres, *args], check=True, capture_output=True, text=True)

    data, log = root / "data", root / "server.log"
    pg(str(PG_BIN / "initdb"), "-D", str(data), "-U", "postgres", "-A", "trust", "-E", "UTF8", "--locale=C")
    # Trust, but only on the unix socket (in `root`, private to postgres) and on 127.0.0.1.
    (data / "pg_hba.conf").write_text("local all all trust\nhost all all 127.0.0.1/32 trust\n")
    port = free_port()
    options = f"-c listen_addresses=127.0.0.1 -c port={port} -k {root} -c fsync=on"
    try:
        pg(str(PG_BIN / "pg_ctl"), "start", "-w", "-D", str(data), "-l", str(log), "-o", options)
    except subprocess.CalledProcessError as err:
        server_log = log.read_text() if log.exists() else ""
        shutil.rmtree(root, ignore_errors=True)
        pytest.fail(f"PostgreSQL did not start: {err.stderr}\n{server_log}", pytrace=False)
    try:
        yield _create_database(f"postgresql+psycopg://postgres@127.0.0.1:{port}/postgres", "roadgrip_test")
    finally:
        pg(str(PG_BIN / "pg_ctl"), "stop", "-w", "-m", "fast", "-D", str(data))
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def postgres_database_url(postgres_url):
    """The URL of a new, empty database on the session's PostgreSQL server, dropped after the test."""
    name = f"test_{uuid.uuid4().hex[:16]}"
    yield _create_database(postgres_url, name)
    _drop_database(postgres_url, name)


@pytest.fixture(params=["sqlite", "postgresql"])
def storage_url(request, tmp_path):
    """A fresh, empty database: an SQLite file, or a new database on the session's PostgreSQL server."""
    if request.param == "sqlite":
        return f"sqlite:///{tmp_path / 'roadgrip.db'}"
    return request.getfixturevalue("postgres_database_url")


@pytest.fixture
def storage(storage_url):
    """An open storage on `storage_url`, closed after the test."""
    opened = open_storage(storage_url)
    yield opened
    opened.close()
