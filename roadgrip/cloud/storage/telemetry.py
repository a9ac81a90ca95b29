"""The telemetry and estimates tables: `write_batch`, the ingest's hot path (both tables in one transaction,
idempotent, fenced by partition in cluster mode), and the queries of what was stored.

On PostgreSQL the rows go in by COPY (`_copy_new`): the rows become an Arrow table, written as CSV by pyarrow's C++
writer and streamed through psycopg's `cursor.copy`, with no per-row SQL parameters; COPY cannot skip stored keys, so
it runs in a savepoint and a repeat (a unique violation) rolls it back and falls back to the INSERT path. SQLite (no
COPY) takes the multi-row INSERTs."""

from __future__ import annotations

import itertools
import operator
from collections.abc import Mapping
from dataclasses import dataclass

import psycopg
import pyarrow as pa
import pyarrow.csv
import sqlalchemy as sa
from sqlalchemy import Table, func, select
from sqlalchemy.engine import Connection

from roadgrip.cloud.storage.base import Database, StorageUnavailable, check_limit, checked_rows
from roadgrip.cloud.storage.partitions import check_fences
from roadgrip.cloud.storage.schema import KEY, estimates_table, telemetry_table, vehicles_table, warnings_table
from roadgrip.data.schema import ESTIMATE, TELEMETRY

# the Arrow schema of each table's rows, from the one schema its columns come from (roadgrip/data/schema.py)
_ARROW = {
    "telemetry": pa.schema([pa.field(c.name, c.type) for c in TELEMETRY]),
    "estimates": pa.schema([pa.field(c.name, c.type) for c in ESTIMATE]),
}
_CSV = pyarrow.csv.WriteOptions(include_header=False)

# rows per INSERT statement, largest first: 1,024 x 17 parameters fit SQLite's limit (32,766) and PostgreSQL's (65,535)
INSERT_SIZES = tuple(2**k for k in range(10, -1, -1))


@dataclass(frozen=True)
class Written:
    """What one `Storage.write_batch` newly stored."""

    telemetry: int  # telemetry rows inserted
    estimates: int  # estimate rows inserted
    already_stored: frozenset[tuple[str, int]]  # (vehicle_id, timestamp_ms) of telemetry rows stored before the call


class _Repeats(Exception):
    """Raised inside write_batch's first try, to roll it back: some telemetry rows were stored already."""


class Telemetry:
    """Telemetry and estimates on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db
        self.use_copy = db.dialect == "postgresql"  # COPY on the hot path; else (SQLite) multi-row INSERTs
        self._insert_sqls: dict[tuple[str, int, bool], str] = {}  # (table, rows, RETURNING) -> multi-row INSERT

    def write_batch(
        self, telemetry: list[dict], estimates: list[dict], fences: Mapping[int, int] | None = None
    ) -> Written:
        """Store telemetry rows (keys: TELEMETRY's column names; optional ones may be None or absent) and estimate
        rows (keys: the estimates table's columns; position and h3_cell may be None or absent) in one transaction.
        Rows whose (vehicle_id, timestamp_ms) is stored already, or came earlier in the same list, are skipped.
        Returns what was newly stored and which telemetry rows were stored before (`Written`). Values go to the
        database driver as they are: Python str, int, float, bool (not 0/1 for the flags) or None.

        `fences` (partition -> the epoch `take_partition` gave the writer): the transaction first reads those
        partitions' epochs, locked against a take until it commits, and raises Fenced, storing nothing, if another
        worker has taken one since.

        Two tries at most. The first counts the rows each INSERT stored (`rowcount`); when every telemetry row was
        new (the usual case) that is all. Otherwise it is rolled back and done again with RETURNING, which names the
        rows inserted. RETURNING is not used at first because SQLite hands each returned row over in a step of its
        own, releasing Python's interpreter lock around each: with another thread busy, each step then waits for
        the lock (up to `sys.getswitchinterval()`, 5 ms), and 500-row INSERTs fell from 35,000 rows/s to 6,000
        (`python results/trials/reliability/sqlite_returning_gil.py`)."""
        telemetry = checked_rows("telemetry", telemetry, telemetry_table)
        estimates = checked_rows("estimate", estimates, estimates_table)
        try:
            with self._db.transaction() as conn:
                check_fences(conn, fences)
                if self.use_copy:
                    if self._copy_new(conn, telemetry_table, telemetry) is None:
                        raise _Repeats
                    stored = self._copy_new(conn, estimates_table, estimates)
                    if stored is None:
                        stored = self._insert_new(conn, estimates_table, estimates)
                    return Written(len(telemetry), stored, frozenset())
                stored = self._insert_new(conn, telemetry_table, telemetry)
                if stored < len(telemetry):
                    raise _Repeats
                return Written(stored, self._insert_new(conn, estimates_table, estimates), frozenset())
        except _Repeats:
            pass
        with self._db.transaction() as conn:
            check_fences(conn, fences)
            inserted = set(self._insert_new(conn, telemetry_table, telemetry, returning=True))
            return Written(
                len(inserted),
                self._insert_new(conn, estimates_table, estimates),
                frozenset(
                    key for row in telemetry if (key := (row["vehicle_id"], row["timestamp_ms"])) not in inserted
                ),
            )

    def _copy_new(self, conn: Connection, table: Table, rows: list[dict]) -> int | None:
        """PostgreSQL: COPY `rows` into `table` in a savepoint: the number stored (all of them), or None when one of
        them was stored already or came twice (the savepoint rolled back, nothing of them stored)."""
        if not rows:
            return 0
        arrow = pa.Table.from_pylist(rows, schema=_ARROW[table.name])
        sink = pa.BufferOutputStream()
        pyarrow.csv.write_csv(arrow, sink, _CSV)
        columns = ", ".join(arrow.column_names)
        try:
            with (
                conn.begin_nested(),
                conn.connection.driver_connection.cursor() as cursor,
                cursor.copy(f"COPY {table.name} ({columns}) FROM STDIN (FORMAT csv)") as copy,
            ):
                copy.write(sink.getvalue())
        except psycopg.errors.UniqueViolation:
            return None
        except (psycopg.IntegrityError, psycopg.DataError) as err:  # what `reported` says of an INSERT's
            raise ValueError(f"rejected by database {self._db.where}: {err}") from err
        except (psycopg.OperationalError, psycopg.InterfaceError) as err:
            raise StorageUnavailable(f"database {self._db.where} unavailable: {err}") from err
        return len(rows)

    def _insert_new(self, conn: Connection, table: Table, rows: list[dict], returning: bool = False):
        """Insert `rows`, skipping keys stored already: the number inserted, or with `returning` the keys inserted.
        Multi-row INSERTs of INSERT_SIZES rows, each compiled once by SQLAlchemy for this database and then executed
        with its parameters as they are: the per-row work of `conn.execute(query, rows)` (SQLAlchemy's
        "insertmanyvalues") would halve the write rate."""
        values_of = operator.itemgetter(*(c.name for c in table.columns))
        inserted, keys = 0, []
        start = 0
        for size in INSERT_SIZES:
            while len(rows) - start >= size:
                values = tuple(itertools.chain.from_iterable(map(values_of, rows[start : start + size])))
                result = conn.exec_driver_sql(self.insert_sql(table, size, returning), values)
                if returning:
                    keys += [tuple(key) for key in result.all()]
                else:
                    inserted += result.rowcount
                start += size
        return keys if returning else inserted

    def insert_sql(self, table: Table, n_rows: int, returning: bool) -> str:
        """The SQL of an INSERT of `n_rows` rows of `table` (telemetry or estimates) that skips stored keys, its
        parameters row after row in the table's column order; with `returning`, it returns the keys inserted."""
        if (table.name, n_rows, returning) not in self._insert_sqls:
            names = [[f"r{i}_{c.name}" for c in table.columns] for i in range(n_rows)]
            values = [{c.name: sa.bindparam(name) for c, name in zip(table.columns, row)} for row in names]
            query = self._db.insert(table).values(values).on_conflict_do_nothing(index_elements=KEY)
            if returning:
                query = query.returning(table.c.vehicle_id, table.c.timestamp_ms)
            compiled = query.compile(dialect=self._db.engine.dialect)
            if list(compiled.positiontup or ()) != [name for row in names for name in row]:
                raise RuntimeError(f"{self._db.dialect}: INSERT parameters not in row order, cannot pass them flat")
            self._insert_sqls[(table.name, n_rows, returning)] = compiled.string
        return self._insert_sqls[(table.name, n_rows, returning)]

    def _range(self, table: Table, vehicle_id: str, start_ms: int | None, end_ms: int | None, limit: int):
        check_limit(limit)
        query = select(table).where(table.c.vehicle_id == vehicle_id)
        if start_ms is not None:
            query = query.where(table.c.timestamp_ms >= start_ms)
        if end_ms is not None:
            query = query.where(table.c.timestamp_ms < end_ms)
        return self._db.all(query.order_by(table.c.timestamp_ms).limit(limit))

    def estimates(
        self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None, limit: int = 10000
    ) -> list[dict]:
        """The estimates of `vehicle_id` with start_ms <= timestamp_ms < end_ms (either bound may be None), oldest
        first, at most `limit`."""
        return self._range(estimates_table, vehicle_id, start_ms, end_ms, limit)

    def estimates_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        """The estimates of all vehicles with timestamp_ms >= since_ms, oldest first, at most `limit`."""
        check_limit(limit)
        c = estimates_table.c
        return self._db.all(
            select(estimates_table)
            .where(c.timestamp_ms >= since_ms)
            .order_by(c.timestamp_ms, c.vehicle_id)
            .limit(limit)
        )

    def latest_estimates(self) -> list[dict]:
        """The newest estimate of every vehicle with a stored profile and an estimate, by vehicle_id.

        One query, driven by the vehicles table: `(vehicle_id, timestamp_ms) IN (each vehicle with the max(timestamp_ms)
        of its estimates)`, the max a correlated subquery that reads one entry of the primary key index, and each row
        then read by its key: both databases plan it so (EXPLAIN checked), 2.6 ms on PostgreSQL and 4 ms on SQLite for
        200 vehicles and 400,000 estimates, growing with the vehicles, not the estimates. Grouping the estimates table
        by vehicle reads every stored estimate (36 ms on SQLite, 53 ms on PostgreSQL there), and the dashboard asks
        every second. Registration stores a vehicle's profile before it can send, so no vehicle that sends is left
        out."""
        c, v = estimates_table.c, vehicles_table.c
        newer = estimates_table.alias("newer")
        newest = select(
            v.vehicle_id,
            select(func.max(newer.c.timestamp_ms)).where(newer.c.vehicle_id == v.vehicle_id).scalar_subquery(),
        )
        query = select(estimates_table).where(sa.tuple_(c.vehicle_id, c.timestamp_ms).in_(newest))
        return self._db.all(query.order_by(c.vehicle_id))

    def telemetry(
        self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None, limit: int = 100000
    ) -> list[dict]:
        """The telemetry of `vehicle_id` with start_ms <= timestamp_ms < end_ms, oldest first, at most `limit`."""
        return self._range(telemetry_table, vehicle_id, start_ms, end_ms, limit)

    def counts(self) -> dict[str, int]:
        """Rows in each table: telemetry, estimates, vehicles (with a profile), warnings."""
        tables = {
            "telemetry": telemetry_table,
            "estimates": estimates_table,
            "vehicles": vehicles_table,
            "warnings": warnings_table,
        }
        query = select(
            *(select(func.count()).select_from(t).scalar_subquery().label(name) for name, t in tables.items())
        )
        return self._db.all(query)[0]

    def telemetry_extent(self) -> dict[str, tuple[int, int, int]]:
        """vehicle_id -> (rows, first timestamp_ms, last timestamp_ms) of its stored telemetry."""
        c = telemetry_table.c
        rows = self._db.all(
            select(
                c.vehicle_id,
                func.count().label("n"),
                func.min(c.timestamp_ms).label("first"),
                func.max(c.timestamp_ms).label("last"),
            ).group_by(c.vehicle_id)
        )
        return {row["vehicle_id"]: (row["n"], row["first"], row["last"]) for row in rows}

    def latest_timestamps(self) -> dict[str, int]:
        """vehicle_id -> timestamp_ms of its newest stored telemetry row."""
        c = telemetry_table.c
        rows = self._db.all(select(c.vehicle_id, func.max(c.timestamp_ms).label("latest")).group_by(c.vehicle_id))
        return {row["vehicle_id"]: row["latest"] for row in rows}
