"""The cloud platform's database: telemetry, estimates, vehicle profiles, credentials and warnings (DESIGN 3.6).

One code path (SQLAlchemy Core) for two databases: an SQLite file by default (`sqlite:///PATH`: WAL journal,
synchronous=NORMAL, foreign keys on, a busy timeout; one writer thread and many reader threads), PostgreSQL through
psycopg 3 when given its URL (`postgresql://` or `postgresql+psycopg://`). `open_storage(url)` creates the tables that
are missing and returns a `Storage`, whose methods are safe to call from several threads.

| table | key | columns |
| --- | --- | --- |
| telemetry | vehicle_id, timestamp_ms | the columns of `roadgrip.data.schema.TELEMETRY` (wire format v1, DESIGN 3.1), SI units |
| estimates | vehicle_id, timestamp_ms | mu, mu_lower, mu_upper (the 90% interval), excited, estimator (DESIGN 3.4), mu_proven (what the car's acceleration proves; null from an estimator without the guard); latitude_deg, longitude_deg and h3_cell, null where unknown; with PostGIS also `geom` (below) |
| vehicles | vehicle_id | profile (JSON, the fields of DESIGN 3.2), updated_ms |
| credentials | name | role (vehicle, reader, admin or station), secret_hash, vehicle_id (vehicles only), revoked, created_ms |
| warnings | warning_id | cell (H3), status ("active" while in force), detection_ms, updated_ms, message (JSON) |
| estimator_states | vehicle_id, estimator | state (JSON: the estimator's `state_to_dict`, packed by roadgrip/cloud/pipeline/checkpoints.py), updated_ms |
| map_cells | cell | cluster mode: region (its H3 parent), last_ms (its newest evidence), updated_ms, state (JSON: `FrictionMap.cell_states`), written by the region's owner (roadgrip/cloud/cluster/regions.py) |
| region_owners | region_queue | cluster mode: epoch, owner, taken_ms of each region queue (fencing, as partition_owners) |
| counters | name | value: cluster mode's shared counters (`action_sequence_number`: the regions' DENM ActionIDs) |
| station_reports | station_id, timestamp_ms | a roadside station's report (roadgrip/cloud/domain/stations.py: position, surface_state, surface_temperature_c, water_film_thickness_mm, friction, friction_uncertainty), the evidence it gave (mu, mu_lower, mu_upper; null for none) and its covered cells (JSON list), received_ms |

Times are integers, milliseconds since the Unix epoch (UTC). Telemetry and estimates are written together by
`write_batch`, in one transaction, and a row whose (vehicle_id, timestamp_ms) is stored already is skipped: sending a
batch twice stores it once. No foreign keys tie the tables together: a vehicle may send before its profile is stored.
A database made by an older version opens: `open_storage` creates the tables it lacks (estimator_states came later)
and adds the columns it lacks (ADDED_COLUMNS: estimates.mu_proven came later; older rows hold null there).

On PostgreSQL with the PostGIS extension available, estimates get a generated column `geom geometry(Point,4326)` (null
where the position is) with a GiST index, for spatial queries by other tools; `Storage.postgis` says whether it is
there. Without PostGIS everything else works the same.

Failures to reach the database raise `StorageUnavailable`; bad arguments raise `ValueError`.
"""

from __future__ import annotations

import itertools
import logging
import operator
import time
from collections import Counter
from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import psycopg
import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy import Column, Table, exc, func, select, text
from sqlalchemy.dialects import postgresql, sqlite
from sqlalchemy.engine import URL, Connection, Engine, make_url

from roadgrip.data.schema import TELEMETRY

log = logging.getLogger(__name__)

ROLES = ("vehicle", "reader", "admin", "station")
ACTIVE = "active"  # the warning status that `warnings(active_only=True)` selects
SQLITE_BUSY_TIMEOUT_MS = 10_000  # how long a writer waits for another one's lock before giving up
CONNECT_TIMEOUT_S = 5  # PostgreSQL: how long to wait for the server before calling it unavailable
KEY = ("vehicle_id", "timestamp_ms")
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


class Fenced(RuntimeError):
    """A fenced write named a partition that another worker has taken since (`Storage.write_batch`): nothing of it
    was stored."""

    def __init__(self, partitions: set[int]):
        super().__init__(f"partitions {sorted(partitions)} were taken by another worker")
        self.partitions = partitions


class StorageUnavailable(RuntimeError):
    """The database cannot be reached or used (server down, file not writable, locked for too long)."""


@dataclass(frozen=True)
class Credential:
    name: str  # login name: a vehicle's id for vehicles, a free name for readers and admins
    role: str  # one of ROLES
    secret_hash: str
    vehicle_id: str | None  # the vehicle a "vehicle" credential speaks for; None for the other roles
    revoked: bool
    created_ms: int


def _sql_type(column):
    """The SQL type of a telemetry schema column, from its pyarrow type."""
    for is_type, sql_type in ((pa.types.is_string, sa.String), (pa.types.is_integer, sa.BigInteger),
                              (pa.types.is_floating, sa.Float), (pa.types.is_boolean, sa.Boolean)):
        if is_type(column.type):
            return sql_type()
    raise TypeError(f"telemetry column {column.name}: no SQL type for pyarrow type {column.type}")


_JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
metadata = sa.MetaData()
# Plain rowid tables on SQLite, not WITHOUT ROWID: a batch holds samples of many vehicles, and a table clustered by
# (vehicle_id, timestamp_ms) took them three times slower (1,000 vehicles, 1,000-row batches).
telemetry_table = Table(
    "telemetry", metadata,
    *(Column(c.name, _sql_type(c), nullable=not c.required) for c in TELEMETRY),
    sa.PrimaryKeyConstraint(*KEY))
estimates_table = Table(
    "estimates", metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("timestamp_ms", sa.BigInteger, nullable=False),
    Column("mu", sa.Float, nullable=False),
    Column("mu_lower", sa.Float, nullable=False),
    Column("mu_upper", sa.Float, nullable=False),
    Column("excited", sa.Boolean, nullable=False),
    Column("estimator", sa.String, nullable=False),
    Column("mu_proven", sa.Float),
    Column("latitude_deg", sa.Float),
    Column("longitude_deg", sa.Float),
    Column("h3_cell", sa.String),
    sa.PrimaryKeyConstraint(*KEY), sa.Index("ix_estimates_timestamp_ms", "timestamp_ms"))
vehicles_table = Table(
    "vehicles", metadata,
    Column("vehicle_id", sa.String, primary_key=True),
    Column("profile", _JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False))
credentials_table = Table(
    "credentials", metadata,
    Column("name", sa.String, primary_key=True),
    Column("role", sa.String, sa.CheckConstraint(f"role IN {ROLES}", name="ck_credentials_role"), nullable=False),
    Column("secret_hash", sa.String, nullable=False),
    Column("vehicle_id", sa.String),
    Column("revoked", sa.Boolean, nullable=False),
    Column("created_ms", sa.BigInteger, nullable=False))
warnings_table = Table(
    "warnings", metadata,
    Column("warning_id", sa.String, primary_key=True),
    Column("cell", sa.String, nullable=False),
    Column("status", sa.String, nullable=False),
    Column("detection_ms", sa.BigInteger, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    Column("message", _JSON, nullable=False))

# Each vehicle's estimator state (its self-calibration), one row per estimator name: a service switched from one
# estimator to another and back finds the first one's state again (roadgrip/cloud/pipeline/checkpoints.py).
estimator_states_table = Table(
    "estimator_states", metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("estimator", sa.String, nullable=False),
    Column("state", _JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "estimator"))

# Cluster workers' ownership of partitions (roadgrip/cloud/cluster/worker.py): a worker that takes a partition raises its
# epoch; a write fenced with an older epoch fails (`Storage.write_batch`'s `fences`), so that a worker that lost a
# partition without noticing stores nothing of it after the next owner has begun.
partition_owners_table = Table(
    "partition_owners", metadata,
    Column("partition_id", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False))

# Cluster mode's friction map (roadgrip/cloud/cluster/regions.py): each cell's state as its region's owner last saved it
# (`FrictionMap.cell_states`), for the API replicas to render the map from and a new owner to go on from; the owners of
# region queues, with an epoch each, fence those writes and the region's warnings as partition_owners fence telemetry.
map_cells_table = Table(
    "map_cells", metadata,
    Column("cell", sa.String, primary_key=True),
    Column("region", sa.String, nullable=False),
    Column("last_ms", sa.BigInteger, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    Column("state", _JSON, nullable=False),
    sa.Index("ix_map_cells_region", "region"), sa.Index("ix_map_cells_last_ms", "last_ms"))
region_owners_table = Table(
    "region_owners", metadata,
    Column("region_queue", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False))

# Counters shared by the processes of a cluster: the DENM ActionID sequence numbers of the regions' warning engines
# (one originating station, many engines).
counters_table = Table(
    "counters", metadata,
    Column("name", sa.String, primary_key=True),
    Column("value", sa.BigInteger, nullable=False))

# columns added after their table was first released: (table, column), added by open_storage where missing
ADDED_COLUMNS = ((estimates_table, "mu_proven"),)

# Roadside stations' reports (roadgrip/cloud/domain/stations.py), as validated, with the evidence the service drew from them.
station_reports_table = Table(
    "station_reports", metadata,
    Column("station_id", sa.String, nullable=False),
    Column("timestamp_ms", sa.BigInteger, nullable=False),
    Column("latitude_deg", sa.Float, nullable=False),
    Column("longitude_deg", sa.Float, nullable=False),
    Column("surface_state", sa.String, nullable=False),
    Column("surface_temperature_c", sa.Float),
    Column("water_film_thickness_mm", sa.Float),
    Column("friction", sa.Float),
    Column("friction_uncertainty", sa.Float),
    Column("mu", sa.Float),
    Column("mu_lower", sa.Float),
    Column("mu_upper", sa.Float),
    Column("cells", _JSON, nullable=False),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("station_id", "timestamp_ms"),
    sa.Index("ix_station_reports_timestamp_ms", "timestamp_ms"))

POSTGIS_DDL = (
    ("ALTER TABLE estimates ADD COLUMN IF NOT EXISTS geom geometry(Point, 4326) "
     "GENERATED ALWAYS AS (ST_SetSRID(ST_MakePoint(longitude_deg, latitude_deg), 4326)) STORED"),
    "CREATE INDEX IF NOT EXISTS ix_estimates_geom ON estimates USING GIST (geom)",
)


SCHEMA_LOCK_KEY = 0x726F6164  # "road": the advisory lock of `_schema_lock`


def _now_ms() -> int:
    return time.time_ns() // 1_000_000


def normalise_url(url: str) -> URL:
    """`url` with its driver made explicit (sqlite+pysqlite, postgresql+psycopg); ValueError if it is not supported."""
    try:
        sa_url = make_url(url)
    except exc.ArgumentError:
        raise ValueError(f"storage URL {url.partition('://')[0]}://... is not a database URL: "
                         "use sqlite:///PATH or postgresql://USER@HOST:PORT/DATABASE") from None
    backend, _, driver = sa_url.drivername.partition("+")
    if backend in ("postgresql", "postgres") and driver in ("", "psycopg"):
        return sa_url.set(drivername="postgresql+psycopg")
    if backend == "sqlite" and driver in ("", "pysqlite"):
        if sa_url.database in (None, "", ":memory:"):
            raise ValueError(f"storage URL {url!r}: SQLite storage needs a file, sqlite:///PATH")
        return sa_url.set(drivername="sqlite+pysqlite")
    raise ValueError(f"unsupported storage URL scheme {sa_url.drivername!r}: "
                     "use sqlite:///PATH or postgresql://USER@HOST:PORT/DATABASE")


@contextmanager
def _reported(where: str) -> Iterator[None]:
    """Turn the database's operational failures into StorageUnavailable, and rejected values (a constraint, a type)
    into ValueError."""
    try:
        yield
    except (exc.OperationalError, exc.InterfaceError, exc.DisconnectionError, exc.TimeoutError) as err:
        raise StorageUnavailable(f"database {where} unavailable: {getattr(err, 'orig', None) or err}") from err
    except (exc.IntegrityError, exc.DataError) as err:
        raise ValueError(f"rejected by database {where}: {err.orig}") from err


def _sqlite_pragmas(dbapi_connection, connection_record) -> None:
    cursor = dbapi_connection.cursor()
    for pragma in ("journal_mode=WAL", "synchronous=NORMAL", "foreign_keys=ON",
                   f"busy_timeout={SQLITE_BUSY_TIMEOUT_MS}"):
        cursor.execute(f"PRAGMA {pragma}")
    cursor.close()


def _checked_rows(kind: str, rows: list[dict], table: Table) -> list[dict]:
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


def _check_limit(limit: int) -> None:
    if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
        raise ValueError(f"limit must be a positive integer, got {limit!r}")


class Storage:
    """The tables above on one database; made by `open_storage`. Thread-safe: every call takes a pooled connection."""

    def __init__(self, url: str, engine: Engine, postgis: bool):
        self.url = url
        self.dialect = engine.dialect.name
        self.postgis = postgis
        self._engine = engine
        self._where = engine.url.render_as_string(hide_password=True)
        self._insert = postgresql.insert if self.dialect == "postgresql" else sqlite.insert
        self._insert_sqls: dict[tuple[str, int, bool], str] = {}  # (table, rows, RETURNING) -> multi-row INSERT

    def __repr__(self) -> str:
        return f"Storage({self._where!r}, postgis={self.postgis})"

    def close(self) -> None:
        self._engine.dispose()

    @contextmanager
    def _transaction(self) -> Iterator[Connection]:
        with _reported(self._where), self._engine.begin() as conn:
            yield conn

    def _all(self, query) -> list[dict]:
        with _reported(self._where), self._engine.connect() as conn:
            return [dict(row) for row in conn.execute(query).mappings()]

    def _scalar(self, query):
        with _reported(self._where), self._engine.connect() as conn:
            return conn.execute(query).scalar()

    def ping(self) -> None:
        """Raise StorageUnavailable unless the database answers."""
        self._scalar(text("SELECT 1"))

    # ------------------------------------------------------------------------------------ credentials and vehicles

    def add_credential(self, name: str, role: str, secret_hash: str, vehicle_id: str | None = None,
                       before_commit: Callable[[], None] | None = None) -> None:
        """Store a new credential. A "vehicle" credential's name is its vehicle's id (vehicle_id defaults to it);
        readers and admins have no vehicle_id. ValueError if `name` is taken. `before_commit` (as in
        `register_vehicles`) runs once the row is in, before the commit."""
        if not isinstance(name, str) or not name:
            raise ValueError(f"credential name must be a non-empty string, got {name!r}")
        if role not in ROLES:
            raise ValueError(f"credential role must be one of {ROLES}, got {role!r}")
        if role == "vehicle":
            vehicle_id = name if vehicle_id is None else vehicle_id
            if vehicle_id != name:
                raise ValueError(f"a vehicle credential is named by its vehicle's id: name {name!r}, "
                                 f"vehicle_id {vehicle_id!r}")
        elif vehicle_id is not None:
            raise ValueError(f"a {role} credential has no vehicle_id, got {vehicle_id!r}")
        row = {"name": name, "role": role, "secret_hash": secret_hash, "vehicle_id": vehicle_id, "revoked": False,
               "created_ms": _now_ms()}
        insert = self._insert(credentials_table).values(row).on_conflict_do_nothing()
        with self._transaction() as conn:
            added = conn.execute(insert.returning(credentials_table.c.name)).first()
            if added is None:
                raise ValueError(f"a credential named {name!r} exists already")
            if before_commit is not None:
                before_commit()

    def credential(self, name: str) -> Credential | None:
        rows = self._all(select(credentials_table).where(credentials_table.c.name == name))
        return Credential(**rows[0]) if rows else None

    def credentials(self) -> list[Credential]:
        return [Credential(**row) for row in self._all(select(credentials_table).order_by(credentials_table.c.name))]

    def revoke_credential(self, name: str) -> bool:
        """Revoke credential `name`; True if it existed and was active."""
        c = credentials_table.c
        with self._transaction() as conn:
            query = credentials_table.update().where(c.name == name, c.revoked.is_(False)).values(revoked=True)
            return conn.execute(query).rowcount == 1

    def set_secret_hash(self, name: str, secret_hash: str) -> None:
        """Replace credential `name`'s secret hash (revoked or not); ValueError if there is no such credential."""
        with self._transaction() as conn:
            query = credentials_table.update().where(credentials_table.c.name == name)
            if conn.execute(query.values(secret_hash=secret_hash)).rowcount != 1:
                raise ValueError(f"no credential named {name!r}")

    def put_vehicle(self, vehicle_id: str, profile: dict) -> None:
        """Store (or replace) the profile of `vehicle_id`: a JSON-able dict of DESIGN 3.2 fields."""
        if not isinstance(profile, dict):
            raise TypeError(f"profile of vehicle {vehicle_id!r} must be a dict, got {type(profile).__name__}")
        with self._transaction() as conn:
            conn.execute(self._profile_upsert(),
                         {"vehicle_id": vehicle_id, "profile": profile, "updated_ms": _now_ms()})

    def _profile_upsert(self):
        """INSERT of vehicle profiles that replaces a stored one (parameters: vehicle_id, profile, updated_ms)."""
        insert = self._insert(vehicles_table)
        return insert.on_conflict_do_update(
            index_elements=["vehicle_id"],
            set_={"profile": insert.excluded.profile, "updated_ms": insert.excluded.updated_ms})

    def register_vehicles(self, vehicles: list[tuple[str, dict, str]],
                          before_commit: Callable[[], None] | None = None) -> None:
        """For each (vehicle_id, profile, secret_hash): store the profile (replacing a stored one) and a new "vehicle"
        credential named vehicle_id, all in one transaction, so that a failure part way leaves none of them stored
        (nor a credential whose secret nobody received). ValueError, storing nothing, when a vehicle_id is given twice
        or its credential name is taken. `before_commit` runs once every row is in, before the commit (the cluster
        creates the vehicles' broker users there: roadgrip/cloud/cluster/api_backend.py); what it raises rolls it all back."""
        ids = [vehicle_id for vehicle_id, _, _ in vehicles]
        twice = sorted(v for v, n in Counter(ids).items() if n > 1)
        if twice:
            raise ValueError(f"vehicle_id(s) given twice: {', '.join(twice[:10])}")
        for vehicle_id, profile, _ in vehicles:
            if not isinstance(profile, dict):
                raise TypeError(f"profile of vehicle {vehicle_id!r} must be a dict, got {type(profile).__name__}")
        if not vehicles:
            return
        now_ms = _now_ms()
        credentials = self._insert(credentials_table).on_conflict_do_nothing().returning(credentials_table.c.name)
        with self._transaction() as conn:
            added = {row[0] for row in conn.execute(credentials, [
                {"name": v, "role": "vehicle", "secret_hash": h, "vehicle_id": v, "revoked": False,
                 "created_ms": now_ms} for v, _, h in vehicles])}
            if len(added) < len(vehicles):  # raising rolls the transaction back
                taken = [v for v in ids if v not in added]
                raise ValueError(f"vehicle_id(s) already registered: {', '.join(taken[:10])}")
            conn.execute(self._profile_upsert(),
                         [{"vehicle_id": v, "profile": p, "updated_ms": now_ms} for v, p, _ in vehicles])
            if before_commit is not None:
                before_commit()

    def vehicle_profile(self, vehicle_id: str) -> dict | None:
        return self._scalar(select(vehicles_table.c.profile).where(vehicles_table.c.vehicle_id == vehicle_id))

    def vehicle_ids(self) -> list[str]:
        """The ids of the vehicles with a stored profile, sorted."""
        return [row["vehicle_id"] for row in self._all(
            select(vehicles_table.c.vehicle_id).order_by(vehicles_table.c.vehicle_id))]

    # ------------------------------------------------------------------------------------ telemetry and estimates

    def write_batch(self, telemetry: list[dict], estimates: list[dict],
                    fences: Mapping[int, int] | None = None) -> Written:
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
        (`python scripts/sqlite_returning_gil.py`)."""
        telemetry = _checked_rows("telemetry", telemetry, telemetry_table)
        estimates = _checked_rows("estimate", estimates, estimates_table)
        try:
            with self._transaction() as conn:
                self._check_fences(conn, fences)
                stored = self._insert_new(conn, telemetry_table, telemetry)
                if stored < len(telemetry):
                    raise _Repeats
                return Written(stored, self._insert_new(conn, estimates_table, estimates), frozenset())
        except _Repeats:
            pass
        with self._transaction() as conn:
            self._check_fences(conn, fences)
            inserted = set(self._insert_new(conn, telemetry_table, telemetry, returning=True))
            return Written(len(inserted), self._insert_new(conn, estimates_table, estimates),
                           frozenset(key for row in telemetry if (key := (row["vehicle_id"], row["timestamp_ms"]))
                                     not in inserted))

    def _check_fences(self, conn: Connection, fences: Mapping[int, int] | None) -> None:
        if not fences:
            return
        c = partition_owners_table.c
        query = select(c.partition_id, c.epoch).where(c.partition_id.in_(sorted(fences))).with_for_update(read=True)
        epochs = dict(conn.execute(query).all())
        stale = {p for p, epoch in fences.items() if epochs.get(p) != epoch}
        if stale:
            raise Fenced(stale)

    def take_partition(self, partition_id: int, owner: str) -> int:
        """Raise the partition's epoch (1 when first taken) and name `owner` as its owner; returns the new epoch,
        which the owner's fenced writes carry (`write_batch`). Waits for fenced writes of the partition in progress."""
        insert = self._insert(partition_owners_table).values(partition_id=partition_id, epoch=1, owner=owner,
                                                             taken_ms=_now_ms())
        upsert = insert.on_conflict_do_update(
            index_elements=["partition_id"],
            set_={"epoch": partition_owners_table.c.epoch + 1, "owner": insert.excluded.owner,
                  "taken_ms": insert.excluded.taken_ms}).returning(partition_owners_table.c.epoch)
        with self._transaction() as conn:
            return conn.execute(upsert).scalar_one()

    def partition_owners(self) -> dict[int, str]:
        """partition -> the owner that took it last (`take_partition`), for the partitions taken at least once."""
        c = partition_owners_table.c
        return {row["partition_id"]: row["owner"] for row in self._all(select(c.partition_id, c.owner))}

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
                values = tuple(itertools.chain.from_iterable(map(values_of, rows[start:start + size])))
                result = conn.exec_driver_sql(self._insert_sql(table, size, returning), values)
                if returning:
                    keys += [tuple(key) for key in result.all()]
                else:
                    inserted += result.rowcount
                start += size
        return keys if returning else inserted

    def _insert_sql(self, table: Table, n_rows: int, returning: bool) -> str:
        if (table.name, n_rows, returning) not in self._insert_sqls:
            names = [[f"r{i}_{c.name}" for c in table.columns] for i in range(n_rows)]
            values = [{c.name: sa.bindparam(name) for c, name in zip(table.columns, row)} for row in names]
            query = self._insert(table).values(values).on_conflict_do_nothing(index_elements=KEY)
            if returning:
                query = query.returning(table.c.vehicle_id, table.c.timestamp_ms)
            compiled = query.compile(dialect=self._engine.dialect)
            if list(compiled.positiontup or ()) != [name for row in names for name in row]:
                raise RuntimeError(f"{self.dialect}: INSERT parameters not in row order, cannot pass them flat")
            self._insert_sqls[(table.name, n_rows, returning)] = compiled.string
        return self._insert_sqls[(table.name, n_rows, returning)]

    def _range(self, table: Table, vehicle_id: str, start_ms: int | None, end_ms: int | None, limit: int):
        _check_limit(limit)
        query = select(table).where(table.c.vehicle_id == vehicle_id)
        if start_ms is not None:
            query = query.where(table.c.timestamp_ms >= start_ms)
        if end_ms is not None:
            query = query.where(table.c.timestamp_ms < end_ms)
        return self._all(query.order_by(table.c.timestamp_ms).limit(limit))

    def estimates(self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None,
                  limit: int = 10000) -> list[dict]:
        """The estimates of `vehicle_id` with start_ms <= timestamp_ms < end_ms (either bound may be None), oldest
        first, at most `limit`."""
        return self._range(estimates_table, vehicle_id, start_ms, end_ms, limit)

    def estimates_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        """The estimates of all vehicles with timestamp_ms >= since_ms, oldest first, at most `limit`."""
        _check_limit(limit)
        c = estimates_table.c
        return self._all(select(estimates_table).where(c.timestamp_ms >= since_ms)
                         .order_by(c.timestamp_ms, c.vehicle_id).limit(limit))

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
        newest = select(v.vehicle_id, select(func.max(newer.c.timestamp_ms))
                        .where(newer.c.vehicle_id == v.vehicle_id).scalar_subquery())
        query = select(estimates_table).where(sa.tuple_(c.vehicle_id, c.timestamp_ms).in_(newest))
        return self._all(query.order_by(c.vehicle_id))

    def telemetry(self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None,
                  limit: int = 100000) -> list[dict]:
        """The telemetry of `vehicle_id` with start_ms <= timestamp_ms < end_ms, oldest first, at most `limit`."""
        return self._range(telemetry_table, vehicle_id, start_ms, end_ms, limit)

    def counts(self) -> dict[str, int]:
        """Rows in each table: telemetry, estimates, vehicles (with a profile), warnings."""
        tables = {"telemetry": telemetry_table, "estimates": estimates_table, "vehicles": vehicles_table,
                  "warnings": warnings_table}
        query = select(*(select(func.count()).select_from(t).scalar_subquery().label(name)
                         for name, t in tables.items()))
        return self._all(query)[0]

    def telemetry_extent(self) -> dict[str, tuple[int, int, int]]:
        """vehicle_id -> (rows, first timestamp_ms, last timestamp_ms) of its stored telemetry."""
        c = telemetry_table.c
        rows = self._all(select(c.vehicle_id, func.count().label("n"), func.min(c.timestamp_ms).label("first"),
                                func.max(c.timestamp_ms).label("last")).group_by(c.vehicle_id))
        return {row["vehicle_id"]: (row["n"], row["first"], row["last"]) for row in rows}

    def latest_timestamps(self) -> dict[str, int]:
        """vehicle_id -> timestamp_ms of its newest stored telemetry row."""
        c = telemetry_table.c
        rows = self._all(select(c.vehicle_id, func.max(c.timestamp_ms).label("latest")).group_by(c.vehicle_id))
        return {row["vehicle_id"]: row["latest"] for row in rows}

    # ------------------------------------------------------------------------------------ estimator states

    def put_estimator_states(self, rows: list[dict], fences: Mapping[int, int] | None = None) -> None:
        """Store (or replace) estimator states in one transaction: each row holds vehicle_id, estimator (its name),
        state (a JSON-able dict) and optionally updated_ms (default: now). Of rows with the same key the last wins.
        `fences` as in `write_batch`: Fenced, nothing stored, if another worker has taken one of those partitions
        since (a stale owner's checkpoint must not overwrite the new owner's)."""
        now_ms = _now_ms()
        latest = {}
        for row in rows:
            if not isinstance(row.get("state"), dict):
                raise TypeError(f"state of vehicle {row.get('vehicle_id')!r} must be a dict, got "
                                f"{type(row.get('state')).__name__}")
            latest[(row.get("vehicle_id"), row.get("estimator"))] = {"updated_ms": now_ms, **row}
        if not latest:
            return
        rows = _checked_rows("estimator state", list(latest.values()), estimator_states_table)
        insert = self._insert(estimator_states_table)
        upsert = insert.on_conflict_do_update(index_elements=["vehicle_id", "estimator"],
                                              set_={"state": insert.excluded.state,
                                                    "updated_ms": insert.excluded.updated_ms})
        with self._transaction() as conn:
            self._check_fences(conn, fences)
            conn.execute(upsert, rows)

    def estimator_states(self, vehicle_ids: list[str], estimator: str) -> dict[str, dict]:
        """vehicle_id -> the stored state of estimator `estimator`, for those of `vehicle_ids` that have one."""
        c = estimator_states_table.c
        states: dict[str, dict] = {}
        ids = sorted(set(vehicle_ids))
        for start in range(0, len(ids), 1000):  # well inside every database's limit on parameters
            query = select(c.vehicle_id, c.state).where(c.estimator == estimator,
                                                        c.vehicle_id.in_(ids[start:start + 1000]))
            states.update((row["vehicle_id"], row["state"]) for row in self._all(query))
        return states

    def estimator_state_rows(self) -> list[dict]:
        """Every stored estimator state (vehicle_id, estimator, state, updated_ms), by vehicle and estimator."""
        c = estimator_states_table.c
        return self._all(select(estimator_states_table).order_by(c.vehicle_id, c.estimator))

    # ------------------------------------------------------------------------------------ station reports

    def put_station_reports(self, rows: list[dict]) -> set[tuple[str, int]]:
        """Store station reports in one transaction (keys: the station_reports table's columns; received_ms defaults
        to now); a report whose (station_id, timestamp_ms) is stored already is skipped. Returns the keys newly
        stored."""
        now_ms = _now_ms()
        rows = _checked_rows("station report", [{"received_ms": now_ms, **row} for row in rows],
                             station_reports_table)
        if not rows:
            return set()
        c = station_reports_table.c
        insert = self._insert(station_reports_table).on_conflict_do_nothing().returning(c.station_id, c.timestamp_ms)
        with self._transaction() as conn:
            return {(row[0], row[1]) for row in conn.execute(insert, rows)}

    def latest_station_reports(self) -> list[dict]:
        """The newest report of every station, by station_id."""
        c = station_reports_table.c
        newest = select(c.station_id, func.max(c.timestamp_ms)).group_by(c.station_id)
        query = select(station_reports_table).where(sa.tuple_(c.station_id, c.timestamp_ms).in_(newest))
        return self._all(query.order_by(c.station_id))

    def station_reports_of(self, keys: Iterable[tuple[str, int]]) -> list[dict]:
        """The stored reports with these keys (station_id, timestamp_ms), oldest first; keys not stored are left out."""
        keys = sorted(set(keys))
        if not keys:
            return []
        c = station_reports_table.c
        return self._all(select(station_reports_table).where(sa.tuple_(c.station_id, c.timestamp_ms).in_(keys))
                         .order_by(c.timestamp_ms, c.station_id))

    def station_reports_since(self, since_ms: int, limit: int = 100_000) -> list[dict]:
        """The reports of all stations with timestamp_ms >= since_ms, oldest first, at most `limit`."""
        _check_limit(limit)
        c = station_reports_table.c
        return self._all(select(station_reports_table).where(c.timestamp_ms >= since_ms)
                         .order_by(c.timestamp_ms, c.station_id).limit(limit))

    # ------------------------------------------------------------------------------------ warnings

    def put_warnings(self, rows: list[dict]) -> None:
        """Store (or replace) warnings in one transaction: each row holds warning_id, cell, status, detection_ms,
        updated_ms and message (a JSON-able dict, the DENM-shaped warning). Of rows with the same warning_id the last
        one wins."""
        latest = {}
        for row in rows:
            if not isinstance(row.get("message"), dict):
                raise TypeError(f"message of warning {row.get('warning_id')!r} must be a dict, got "
                                f"{type(row.get('message')).__name__}")
            latest[row["warning_id"]] = row
        if not latest:
            return
        rows = _checked_rows("warning", list(latest.values()), warnings_table)
        insert = self._insert(warnings_table)
        upsert = insert.on_conflict_do_update(
            index_elements=["warning_id"],
            set_={name: insert.excluded[name] for name in ("cell", "status", "detection_ms", "updated_ms", "message")})
        with self._transaction() as conn:
            conn.execute(upsert, rows)

    def put_region_output(self, warnings: list[dict], cells: list[dict], fence: tuple[int, int] | None = None) -> None:
        """Store a region's warnings (rows as `put_warnings` takes them) and map cells (cell, region, last_ms, state;
        updated_ms defaults to now; a stored cell is replaced) in one transaction. `fence` (region queue, the epoch
        `take_region_queue` gave the writer): read under a share lock first; Fenced, storing nothing, if another owner
        has taken that queue since."""
        latest = {}
        for row in warnings:
            if not isinstance(row.get("message"), dict):
                raise TypeError(f"message of warning {row.get('warning_id')!r} must be a dict, got "
                                f"{type(row.get('message')).__name__}")
            latest[row["warning_id"]] = row
        now_ms = _now_ms()
        warnings = _checked_rows("warning", list(latest.values()), warnings_table)
        cells = _checked_rows("map cell", list({row["cell"]: {"updated_ms": now_ms, **row} for row in cells}.values()),
                              map_cells_table)
        if not warnings and not cells:
            return
        with self._transaction() as conn:
            if fence is not None:
                c = region_owners_table.c
                epoch = conn.execute(select(c.epoch).where(c.region_queue == fence[0])
                                     .with_for_update(read=True)).scalar()
                if epoch != fence[1]:
                    raise Fenced({fence[0]})
            if warnings:
                insert = self._insert(warnings_table)
                conn.execute(insert.on_conflict_do_update(index_elements=["warning_id"], set_={
                    name: insert.excluded[name] for name in ("cell", "status", "detection_ms", "updated_ms",
                                                             "message")}), warnings)
            if cells:
                insert = self._insert(map_cells_table)
                conn.execute(insert.on_conflict_do_update(index_elements=["cell"], set_={
                    name: insert.excluded[name] for name in ("region", "last_ms", "updated_ms", "state")}), cells)

    def map_cells(self, region: str | None = None, since_ms: int | None = None) -> list[dict]:
        """Stored map cells (cell, region, last_ms, updated_ms, state), of one region or all, with last_ms >= since_ms
        when given, by cell."""
        c = map_cells_table.c
        query = select(map_cells_table).order_by(c.cell)
        if region is not None:
            query = query.where(c.region == region)
        if since_ms is not None:
            query = query.where(c.last_ms >= since_ms)
        return self._all(query)

    def delete_map_cells(self, region: str, before_ms: int, fence: tuple[int, int] | None = None) -> int:
        """Delete a region's map cells whose newest evidence is older than before_ms (fenced as `put_region_output`);
        how many."""
        c = map_cells_table.c
        with self._transaction() as conn:
            if fence is not None:
                o = region_owners_table.c
                epoch = conn.execute(select(o.epoch).where(o.region_queue == fence[0])
                                     .with_for_update(read=True)).scalar()
                if epoch != fence[1]:
                    raise Fenced({fence[0]})
            return conn.execute(map_cells_table.delete().where(c.region == region, c.last_ms < before_ms)).rowcount

    def next_action_sequence_number(self) -> int:
        """The next DENM ActionID sequence number of the cluster's warnings (0, 1, ... 65535, 0, ...), one atomic
        step of the counter `action_sequence_number`."""
        c = counters_table.c
        insert = self._insert(counters_table).values(name="action_sequence_number", value=0)
        upsert = insert.on_conflict_do_update(index_elements=["name"], set_={"value": (c.value + 1) % 65536})
        with self._transaction() as conn:
            return conn.execute(upsert.returning(c.value)).scalar_one()

    def region_owners(self) -> dict[int, str]:
        """region_queue -> the owner that took it last (region_owners)."""
        c = region_owners_table.c
        return {row["region_queue"]: row["owner"] for row in self._all(select(c.region_queue, c.owner))}

    def take_region_queue(self, region_queue: int, owner: str) -> int:
        """Raise the region queue's epoch (1 when first taken) and name `owner` as its owner; returns the new epoch,
        which the owner's fenced writes carry (`put_region_output`)."""
        insert = self._insert(region_owners_table).values(region_queue=region_queue, epoch=1, owner=owner,
                                                          taken_ms=_now_ms())
        upsert = insert.on_conflict_do_update(
            index_elements=["region_queue"],
            set_={"epoch": region_owners_table.c.epoch + 1, "owner": insert.excluded.owner,
                  "taken_ms": insert.excluded.taken_ms}).returning(region_owners_table.c.epoch)
        with self._transaction() as conn:
            return conn.execute(upsert).scalar_one()

    def warnings(self, active_only: bool = False) -> list[dict]:
        """All warnings (or only those whose status is "active"), by detection time."""
        c = warnings_table.c
        query = select(warnings_table).order_by(c.detection_ms, c.warning_id)
        return self._all(query.where(c.status == ACTIVE) if active_only else query)


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


def _add_missing_columns(conn: Connection) -> None:
    for table, name in ADDED_COLUMNS:
        # the result's keys, not the inspector (which warns about PostGIS's geometry type it cannot reflect)
        if name not in conn.execute(text(f"SELECT * FROM {table.name} LIMIT 0")).keys():
            column = table.c[name]
            conn.execute(text(f"ALTER TABLE {table.name} ADD COLUMN {name} "
                              f"{column.type.compile(dialect=conn.dialect)}"))
            log.info("added column %s.%s to a database of an older version", table.name, name)


def _widen_role_check(conn: Connection) -> None:
    """A database made before the station role has a credentials CHECK that names only the roles of its time, and
    would refuse a station's credential: replace the check with one of ROLES (PostgreSQL: the constraint; SQLite,
    which cannot alter a constraint: the table rebuilt, its rows copied, in the same transaction)."""
    if conn.dialect.name == "postgresql":
        definition = conn.execute(text("SELECT pg_get_constraintdef(oid) FROM pg_constraint "
                                       "WHERE conname = 'ck_credentials_role'")).scalar()
        if definition is not None and "'station'" not in definition:
            conn.execute(text("ALTER TABLE credentials DROP CONSTRAINT ck_credentials_role"))
            conn.execute(text(f"ALTER TABLE credentials ADD CONSTRAINT ck_credentials_role CHECK (role IN {ROLES})"))
            log.info("credentials: role check widened to %s", ROLES)
        return
    definition = conn.execute(text("SELECT sql FROM sqlite_master WHERE type = 'table' AND name = 'credentials'"))
    if "'station'" in definition.scalar():
        return
    conn.execute(text("ALTER TABLE credentials RENAME TO credentials_before_stations"))
    credentials_table.create(conn)
    columns = ", ".join(c.name for c in credentials_table.columns)
    conn.execute(text(f"INSERT INTO credentials ({columns}) SELECT {columns} FROM credentials_before_stations"))
    conn.execute(text("DROP TABLE credentials_before_stations"))
    log.info("credentials: table rebuilt with the role check of %s", ROLES)


@contextmanager
def _schema_lock(engine: Engine) -> Iterator[None]:
    """On PostgreSQL, one process at a time creates or alters the tables: processes opening a new database at once
    (the cluster's workers and API replicas starting together) raced in CREATE TABLE and CREATE EXTENSION, and all but
    one failed on a duplicate key of PostgreSQL's catalog. A session advisory lock held while the schema is made."""
    if engine.dialect.name != "postgresql":
        yield
        return
    with engine.connect() as conn:
        conn.execute(text(f"SELECT pg_advisory_lock({SCHEMA_LOCK_KEY})"))
        try:
            yield
        finally:
            conn.execute(text(f"SELECT pg_advisory_unlock({SCHEMA_LOCK_KEY})"))


def open_storage(url: str) -> Storage:
    """Open the database at `url` (sqlite:///PATH, postgresql://... or postgresql+psycopg://...) and create the
    tables that are missing; the parent folder of an SQLite file is created too."""
    sa_url = normalise_url(url)
    where = sa_url.render_as_string(hide_password=True)
    if sa_url.get_backend_name() == "sqlite":
        try:
            Path(sa_url.database).parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise StorageUnavailable(f"database {where} unavailable: {err}") from err
        engine = sa.create_engine(sa_url)
        sa.event.listen(engine, "connect", _sqlite_pragmas)
    else:
        # Positional $n parameters passed through as they are (psycopg's RawCursor): psycopg's conversion of named
        # parameters is slow for a multi-row INSERT (17 parameters a row) and cut the write rate to a quarter.
        engine = sa.create_engine(sa_url, pool_pre_ping=True, paramstyle="numeric_dollar", connect_args={
            "connect_timeout": CONNECT_TIMEOUT_S, "cursor_factory": psycopg.RawCursor})
    try:
        with _reported(where), _schema_lock(engine):
            postgis = engine.dialect.name == "postgresql" and _enable_postgis(engine, where)
            with engine.begin() as conn:
                metadata.create_all(conn)
                _widen_role_check(conn)
                _add_missing_columns(conn)
                for statement in POSTGIS_DDL if postgis else ():
                    conn.execute(text(statement))
    except BaseException:
        engine.dispose()
        raise
    return Storage(url, engine, postgis)
