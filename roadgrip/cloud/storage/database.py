"""The cloud platform's database (CONTRACTS 3.6): `open_storage(url)` and `Storage`, the facade that every caller outside
storage/ uses, over one small repository per group of tables. This module stays the one to import from: it also
re-exports the schema's tables and the errors.

One code path (SQLAlchemy Core) for two databases: an SQLite file by default (`sqlite:///PATH`: WAL journal,
synchronous=NORMAL, foreign keys on, a busy timeout; one writer thread and many reader threads), PostgreSQL through
psycopg 3 when given its URL (`postgresql://` or `postgresql+psycopg://`); storage/engine.py. `open_storage` brings
the database to the current schema (storage/migrate.py: Alembic, under a lock; a database made by an older roadgrip
is upgraded, keeping its rows) and returns a `Storage`, whose methods are safe to call from several threads.

| module | tables | Storage's methods |
| --- | --- | --- |
| schema.py | all of them (their columns: its docstring) | |
| credentials.py | credentials | add_credential, credential, credentials, revoke_credential, set_secret_hash |
| vehicles.py | vehicles (+ credentials) | put_vehicle, register_vehicles, vehicle_profile, vehicle_ids |
| telemetry.py | telemetry, estimates | write_batch, estimates, estimates_since, latest_estimates, telemetry, counts, telemetry_extent, latest_timestamps |
| partitions.py | partition_owners, counters (workers' heartbeats) | take_partition, partition_owners, heartbeat, worker_heartbeats, end_heartbeat (and the fences of write_batch, put_estimator_states) |
| estimator_states.py | estimator_states | put_estimator_states, estimator_states, estimator_state_rows |
| observations.py | observations, heartbeats | put_edge, put_observations, observations_since, observation_extent, put_heartbeats, latest_heartbeats |
| stations.py | station_reports | put_station_reports, latest_station_reports, station_reports_of, station_reports_since |
| map_warnings.py | warnings, map_cells, region_owners, counters | put_warnings, put_region_output, map_cells, delete_map_cells, next_action_sequence_number, region_owners, take_region_queue, warnings |

Telemetry and estimates are written together by `write_batch`, in one transaction, and a row whose (vehicle_id,
timestamp_ms) is stored already is skipped: sending a batch twice stores it once. On PostgreSQL with the PostGIS
extension available, estimates get a generated column `geom` (storage/migrate.py); `Storage.postgis` says whether it
is there. Without PostGIS everything else works the same.

Failures to reach the database raise `StorageUnavailable`; bad arguments raise `ValueError`.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator, Mapping
from contextlib import contextmanager

from sqlalchemy import Table, text
from sqlalchemy.engine import Connection, Engine

from roadgrip.cloud.storage import migrate
from roadgrip.cloud.storage.base import Database, Fenced, StorageUnavailable
from roadgrip.cloud.storage.credentials import Credential, Credentials
from roadgrip.cloud.storage.engine import make_engine, normalise_url
from roadgrip.cloud.storage.estimator_states import EstimatorStates
from roadgrip.cloud.storage.map_warnings import ACTIVE, MapWarnings
from roadgrip.cloud.storage.observations import Observations
from roadgrip.cloud.storage.partitions import Partitions
from roadgrip.cloud.storage.schema import (
    ROLES,
    counters_table,
    credentials_table,
    estimates_table,
    estimator_states_table,
    heartbeats_table,
    map_cells_table,
    metadata,
    observations_table,
    partition_owners_table,
    region_owners_table,
    station_reports_table,
    telemetry_table,
    vehicles_table,
    warnings_table,
)
from roadgrip.cloud.storage.stations import StationReports
from roadgrip.cloud.storage.telemetry import Telemetry, Written
from roadgrip.cloud.storage.vehicles import Vehicles

__all__ = [
    "ACTIVE",
    "ROLES",
    "Credential",
    "Fenced",
    "Storage",
    "StorageUnavailable",
    "Written",
    "counters_table",
    "credentials_table",
    "estimates_table",
    "estimator_states_table",
    "heartbeats_table",
    "map_cells_table",
    "metadata",
    "normalise_url",
    "observations_table",
    "open_storage",
    "partition_owners_table",
    "region_owners_table",
    "station_reports_table",
    "telemetry_table",
    "vehicles_table",
    "warnings_table",
]


class Storage:
    """The tables of storage/schema.py on one database; made by `open_storage`. Each method is its repository's
    (documented there). Thread-safe: every call takes a pooled connection."""

    def __init__(self, url: str, engine: Engine, postgis: bool):
        self.url = url
        self.dialect = engine.dialect.name
        self.postgis = postgis
        self._engine = engine
        self._db = Database(engine)
        self._where = self._db.where
        self._credentials = Credentials(self._db)
        self._vehicles = Vehicles(self._db)
        self._telemetry = Telemetry(self._db)
        self._partitions = Partitions(self._db)
        self._estimator_states = EstimatorStates(self._db)
        self._stations = StationReports(self._db)
        self._observations = Observations(self._db)
        self._map_warnings = MapWarnings(self._db)

    def __repr__(self) -> str:
        return f"Storage({self._where!r}, postgis={self.postgis})"

    def close(self) -> None:
        self._engine.dispose()

    @contextmanager
    def _transaction(self) -> Iterator[Connection]:
        with self._db.transaction() as conn:
            yield conn

    def _all(self, query) -> list[dict]:
        return self._db.all(query)

    def _scalar(self, query):
        return self._db.scalar(query)

    def ping(self) -> None:
        """Raise StorageUnavailable unless the database answers."""
        self._db.scalar(text("SELECT 1"))

    # ------------------------------------------------------------------------------------ credentials.py

    def add_credential(
        self,
        name: str,
        role: str,
        secret_hash: str,
        vehicle_id: str | None = None,
        before_commit: Callable[[], None] | None = None,
    ) -> None:
        return self._credentials.add_credential(name, role, secret_hash, vehicle_id, before_commit)

    def credential(self, name: str) -> Credential | None:
        return self._credentials.credential(name)

    def credentials(self) -> list[Credential]:
        return self._credentials.credentials()

    def revoke_credential(self, name: str) -> bool:
        return self._credentials.revoke_credential(name)

    def set_secret_hash(self, name: str, secret_hash: str) -> None:
        return self._credentials.set_secret_hash(name, secret_hash)

    # ------------------------------------------------------------------------------------ vehicles.py

    def put_vehicle(self, vehicle_id: str, profile: dict) -> None:
        return self._vehicles.put_vehicle(vehicle_id, profile)

    def register_vehicles(
        self, vehicles: list[tuple[str, dict, str]], before_commit: Callable[[], None] | None = None
    ) -> None:
        return self._vehicles.register_vehicles(vehicles, before_commit)

    def vehicle_profile(self, vehicle_id: str) -> dict | None:
        return self._vehicles.vehicle_profile(vehicle_id)

    def vehicle_ids(self) -> list[str]:
        return self._vehicles.vehicle_ids()

    # ------------------------------------------------------------------------------------ telemetry.py, partitions.py

    def write_batch(
        self, telemetry: list[dict], estimates: list[dict], fences: Mapping[int, int] | None = None
    ) -> Written:
        return self._telemetry.write_batch(telemetry, estimates, fences)

    def _insert_sql(self, table: Table, n_rows: int, returning: bool) -> str:
        return self._telemetry.insert_sql(
            table, n_rows, returning
        )  # for results/trials/reliability/sqlite_returning_gil.py

    def take_partition(self, partition_id: int, owner: str) -> int:
        return self._partitions.take_partition(partition_id, owner)

    def partition_owners(self) -> dict[int, str]:
        return self._partitions.partition_owners()

    def heartbeat(self, owner: str) -> None:
        self._partitions.heartbeat(owner)

    def worker_heartbeats(self) -> dict[str, int]:
        return self._partitions.worker_heartbeats()

    def end_heartbeat(self, owner: str, beats: int | None = None) -> None:
        self._partitions.end_heartbeat(owner, beats)

    def estimates(
        self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None, limit: int = 10000
    ) -> list[dict]:
        return self._telemetry.estimates(vehicle_id, start_ms, end_ms, limit)

    def estimates_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        return self._telemetry.estimates_since(since_ms, limit)

    def latest_estimates(self) -> list[dict]:
        return self._telemetry.latest_estimates()

    def telemetry(
        self, vehicle_id: str, start_ms: int | None = None, end_ms: int | None = None, limit: int = 100000
    ) -> list[dict]:
        return self._telemetry.telemetry(vehicle_id, start_ms, end_ms, limit)

    def counts(self) -> dict[str, int]:
        return self._telemetry.counts()

    def telemetry_extent(self) -> dict[str, tuple[int, int, int]]:
        return self._telemetry.telemetry_extent()

    def latest_timestamps(self) -> dict[str, int]:
        return self._telemetry.latest_timestamps()

    # ------------------------------------------------------------------------------------ estimator_states.py

    def put_estimator_states(self, rows: list[dict], fences: Mapping[int, int] | None = None) -> None:
        return self._estimator_states.put_estimator_states(rows, fences)

    def estimator_states(self, vehicle_ids: list[str], estimator: str) -> dict[str, dict]:
        return self._estimator_states.estimator_states(vehicle_ids, estimator)

    def estimator_state_rows(self) -> list[dict]:
        return self._estimator_states.estimator_state_rows()

    # ------------------------------------------------------------------------------------ stations.py

    def put_station_reports(self, rows: list[dict]) -> set[tuple[str, int]]:
        return self._stations.put_station_reports(rows)

    def latest_station_reports(self) -> list[dict]:
        return self._stations.latest_station_reports()

    def station_reports_of(self, keys: Iterable[tuple[str, int]]) -> list[dict]:
        return self._stations.station_reports_of(keys)

    def station_reports_since(self, since_ms: int, limit: int = 100_000) -> list[dict]:
        return self._stations.station_reports_since(since_ms, limit)

    # ------------------------------------------------------------------------------------ observations.py

    def put_edge(self, observations: list[dict], heartbeats: list[dict]) -> tuple[set[tuple[str, int]], int]:
        return self._observations.put_edge(observations, heartbeats)

    def put_observations(self, rows: list[dict]) -> set[tuple[str, int]]:
        return self._observations.put_observations(rows)

    def observations_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        return self._observations.observations_since(since_ms, limit)

    def observation_extent(self) -> dict[str, tuple[int, int, int]]:
        return self._observations.observation_extent()

    def put_heartbeats(self, rows: list[dict]) -> int:
        return self._observations.put_heartbeats(rows)

    def latest_heartbeats(self) -> list[dict]:
        return self._observations.latest_heartbeats()

    # ------------------------------------------------------------------------------------ map_warnings.py

    def put_warnings(self, rows: list[dict]) -> None:
        return self._map_warnings.put_warnings(rows)

    def put_region_output(self, warnings: list[dict], cells: list[dict], fence: tuple[int, int] | None = None) -> None:
        return self._map_warnings.put_region_output(warnings, cells, fence)

    def map_cells(self, region: str | None = None, since_ms: int | None = None) -> list[dict]:
        return self._map_warnings.map_cells(region, since_ms)

    def delete_map_cells(self, region: str, before_ms: int, fence: tuple[int, int] | None = None) -> int:
        return self._map_warnings.delete_map_cells(region, before_ms, fence)

    def next_action_sequence_number(self) -> int:
        return self._map_warnings.next_action_sequence_number()

    def region_owners(self) -> dict[int, str]:
        return self._map_warnings.region_owners()

    def take_region_queue(self, region_queue: int, owner: str) -> int:
        return self._map_warnings.take_region_queue(region_queue, owner)

    def warnings(self, active_only: bool = False) -> list[dict]:
        return self._map_warnings.warnings(active_only)


def open_storage(url: str) -> Storage:
    """Open the database at `url` (sqlite:///PATH, postgresql://... or postgresql+psycopg://...) and bring it to the
    current schema (storage/migrate.py: the tables created in a new one); the parent folder of an SQLite file is
    created too."""
    engine = make_engine(normalise_url(url))
    try:
        postgis = migrate.upgrade(engine)
    except BaseException:
        engine.dispose()
        raise
    return Storage(url, engine, postgis)
