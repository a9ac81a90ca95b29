"""What every repository of the storage (storage/*.py) shares: the errors it raises (StorageUnavailable, Fenced, and
ValueError for what the database rejects), `Database` (one engine with its transaction and query helpers) and the
checks of rows and limits."""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from sqlalchemy import Table, exc
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import Connection, Engine


class StorageUnavailable(RuntimeError):
    """The database cannot be reached or used (server down, file not writable, locked for too long)."""


class Fenced(RuntimeError):
    """A fenced write named a partition that another worker has taken since (`Storage.write_batch`): nothing of it
    was stored."""

    def __init__(self, partitions: set[int]):
        super().__init__(f"partitions {sorted(partitions)} were taken by another worker")
        self.partitions = partitions


def now_ms() -> int:
    return time.time_ns() // 1_000_000


@contextmanager
def reported(where: str) -> Iterator[None]:
    """Turn the database's operational failures into StorageUnavailable, and rejected values (a constraint, a type)
    into ValueError."""
    try:
        yield
    except (exc.OperationalError, exc.InterfaceError, exc.DisconnectionError, exc.TimeoutError) as err:
        raise StorageUnavailable(f"database {where} unavailable: {getattr(err, 'orig', None) or err}") from err
    except (exc.IntegrityError, exc.DataError) as err:
        raise ValueError(f"rejected by database {where}: {err.orig}") from err


class Database:
    """One engine, shared by the repositories: transactions and reads with the database's failures reported
    (`reported`), and the dialect's INSERT (for ON CONFLICT). Thread-safe: every call takes a pooled connection."""

    def __init__(self, engine: Engine):
        self.engine = engine
        self.dialect = engine.dialect.name
        self.where = engine.url.render_as_string(hide_password=True)
        self.insert = postgresql.insert if self.dialect == "postgresql" else sqlite.insert

    @contextmanager
    def transaction(self) -> Iterator[Connection]:
        with reported(self.where), self.engine.begin() as conn:
            yield conn

    def all(self, query) -> list[dict]:
        with reported(self.where), self.engine.connect() as conn:
            return [dict(row) for row in conn.execute(query).mappings()]

    def scalar(self, query):
        with reported(self.where), self.engine.connect() as conn:
            return conn.execute(query).scalar()


def checked_rows(kind: str, rows: list[dict], table: Table) -> list[dict]:
    """`rows` with every column of `table` present (absent nullable ones as None); ValueError for a missing required
    key or an unknown one."""
    columns = [c.name for c in table.columns]
    allowed = set(columns)
    required = {c.name for c in table.columns if not c.nullable}
    checked = []
    for i, row in enumerate(rows):
        if row.keys() != allowed:
            if unknown := row.keys() - allowed:
                raise ValueError(f"{kind} row {i}: unknown keys {sorted(unknown)}; allowed: {columns}")
            if missing := required - row.keys():
                raise ValueError(f"{kind} row {i}: missing required keys {sorted(missing)}")
            row = {c: row.get(c) for c in columns}
        checked.append(row)
    return checked


def check_limit(limit: int) -> None:
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ValueError(f"limit must be a positive integer, got {limit!r}")
