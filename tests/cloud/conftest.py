"""Fixtures for the cloud platform's tests.

- `postgres_url` (session): a real PostgreSQL 15 server, started once in a temporary directory on 127.0.0.1 at a free port
  and stopped at the end of the session, with an empty database `roadgrip_test`; the URL of that database.
- `postgres_database_url`: a fresh, empty database on that server for one test, dropped after it.
- `storage_url`: parametrized over "sqlite" and "postgresql", so that a test using it runs on both: a fresh SQLite file
  in the test's tmp_path, or `postgres_database_url`.
- `storage`: `roadgrip.cloud.storage.database.open_storage(storage_url)`, closed after the test.
- `datex2_schema` (session): the official DATEX II v3.1 schema set (tests/reference/datex2-v3.1), read once (seconds):
  what the DATEX II documents and routes are validated against.

The server needs the Debian packages of `scripts/install_system_deps.sh`; without them the fixture fails (it never skips),
because "passes on SQLite and PostgreSQL" is part of what the tests check.
"""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest
import xmlschema

from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.storage.local_postgres import LocalPostgres, PostgresUnavailable, create_database, drop_database

DATEX2_XSD = Path(__file__).resolve().parents[1] / "reference" / "datex2-v3.1" / "DATEXII_3_D2Payload.xsd"


@pytest.fixture(scope="session")
def postgres_url():
    """A PostgreSQL 15 server of our own for the session; yields the URL of its empty database `roadgrip_test`."""
    server = LocalPostgres()
    try:
        server.start()
    except PostgresUnavailable as err:
        server.close()
        pytest.fail(str(err), pytrace=False)
    try:
        yield server.create_database("roadgrip_test")
    finally:
        server.close()


@pytest.fixture
def postgres_database_url(postgres_url):
    """The URL of a new, empty database on the session's PostgreSQL server, dropped after the test."""
    name = f"test_{uuid.uuid4().hex[:16]}"
    yield create_database(postgres_url, name)
    drop_database(postgres_url, name)


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


@pytest.fixture(scope="session")
def datex2_schema() -> xmlschema.XMLSchema:
    return xmlschema.XMLSchema(DATEX2_XSD)
