"""The database's tables (CONTRACTS 3.6), as SQLAlchemy Core: the one description of the schema that the repositories
query and the Alembic migrations (storage/migrations/) bring every database to.

| table | key | columns |
| --- | --- | --- |
| telemetry | vehicle_id, timestamp_ms | the columns of `roadgrip.data.schema.TELEMETRY` (wire format v1, CONTRACTS 3.1), SI units |
| estimates | vehicle_id, timestamp_ms | the columns of `roadgrip.data.schema.ESTIMATE`: mu, mu_lower, mu_upper (the 90% interval), excited, estimator (CONTRACTS 3.4), mu_proven (what the car's acceleration proves; null from an estimator without the guard); latitude_deg, longitude_deg and h3_cell, null where unknown; with PostGIS also `geom` (storage/migrate.py) |
| vehicles | vehicle_id | profile (JSON, the fields of CONTRACTS 3.2), updated_ms |
| credentials | name | role (one of ROLES), secret_hash, vehicle_id (vehicles only), revoked, created_ms |
| warnings | warning_id | cell (H3), status ("active" while in force), detection_ms, updated_ms, message (JSON) |
| estimator_states | vehicle_id, estimator | state (JSON: the estimator's `state_to_dict`, packed by roadgrip/cloud/pipeline/checkpoints.py), updated_ms |
| partition_owners | partition_id | cluster mode: epoch, owner, taken_ms of each partition (fencing of telemetry, estimates, estimator states) |
| map_cells | cell | cluster mode: region (its H3 parent), last_ms (its newest evidence), updated_ms, state (JSON: `FrictionMap.cell_states`), written by the region's owner (roadgrip/cloud/cluster/regions.py) |
| region_owners | region_queue | cluster mode: epoch, owner, taken_ms of each region queue (fencing, as partition_owners) |
| counters | name | value: cluster mode's shared counters (`action_sequence_number`: the regions' DENM ActionIDs; `worker:OWNER`: a worker's heartbeat, storage/partitions.py) |
| observations | vehicle_id, last_ms | the columns of `roadgrip.data.schema.OBSERVATION` (an edge vehicle's pass through a cell, CONTRACTS 3.7; evidence and channels as JSON lists), received_ms |
| heartbeats | vehicle_id, timestamp_ms | the columns of `roadgrip.data.schema.HEARTBEAT`, received_ms |
| station_reports | station_id, timestamp_ms | a roadside station's report (roadgrip/cloud/domain/stations.py: position, surface_state, surface_temperature_c, water_film_thickness_mm, friction, friction_uncertainty), the evidence it gave (mu, mu_lower, mu_upper; null for none) and its covered cells (JSON list), received_ms |

Times are integers, milliseconds since the Unix epoch (UTC). No foreign keys tie the tables together: a vehicle may send
before its profile is stored. A change here needs a new revision in storage/migrations/versions/ (the test of the
migrations compares the upgraded database with these tables).
"""

from __future__ import annotations

import pyarrow as pa
import sqlalchemy as sa
from sqlalchemy import Column, Table
from sqlalchemy.dialects import postgresql

from roadgrip.data.schema import ESTIMATE, HEARTBEAT, OBSERVATION, TELEMETRY

ROLES = ("vehicle", "reader", "admin", "station")  # the credential roles the credentials table's check admits
KEY = ("vehicle_id", "timestamp_ms")  # the key of telemetry and estimates


def _sql_type(column):
    """The SQL type of a `roadgrip.data.schema` column, from its pyarrow type."""
    for is_type, sql_type in (
        (pa.types.is_string, sa.String),
        (pa.types.is_integer, sa.BigInteger),
        (pa.types.is_floating, sa.Float),
        (pa.types.is_boolean, sa.Boolean),
    ):
        if is_type(column.type):
            return sql_type()
    if pa.types.is_list(column.type):
        return JSON
    raise TypeError(f"column {column.name}: no SQL type for pyarrow type {column.type}")


JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
metadata = sa.MetaData()
# Plain rowid tables on SQLite, not WITHOUT ROWID: a batch holds samples of many vehicles, and a table clustered by
# (vehicle_id, timestamp_ms) took them three times slower (1,000 vehicles, 1,000-row batches).
telemetry_table = Table(
    "telemetry",
    metadata,
    *(Column(c.name, _sql_type(c), nullable=not c.required) for c in TELEMETRY),
    sa.PrimaryKeyConstraint(*KEY),
)
estimates_table = Table(
    "estimates",
    metadata,
    *(Column(c.name, _sql_type(c), nullable=not c.required) for c in ESTIMATE),
    sa.PrimaryKeyConstraint(*KEY),
    sa.Index("ix_estimates_timestamp_ms", "timestamp_ms"),
)
vehicles_table = Table(
    "vehicles",
    metadata,
    Column("vehicle_id", sa.String, primary_key=True),
    Column("profile", JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
)
credentials_table = Table(
    "credentials",
    metadata,
    Column("name", sa.String, primary_key=True),
    Column("role", sa.String, sa.CheckConstraint(f"role IN {ROLES}", name="ck_credentials_role"), nullable=False),
    Column("secret_hash", sa.String, nullable=False),
    Column("vehicle_id", sa.String),
    Column("revoked", sa.Boolean, nullable=False),
    Column("created_ms", sa.BigInteger, nullable=False),
)
warnings_table = Table(
    "warnings",
    metadata,
    Column("warning_id", sa.String, primary_key=True),
    Column("cell", sa.String, nullable=False),
    Column("status", sa.String, nullable=False),
    Column("detection_ms", sa.BigInteger, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    Column("message", JSON, nullable=False),
)

# Each vehicle's estimator state (its self-calibration), one row per estimator name: a service switched from one
# estimator to another and back finds the first one's state again (roadgrip/cloud/pipeline/checkpoints.py).
estimator_states_table = Table(
    "estimator_states",
    metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("estimator", sa.String, nullable=False),
    Column("state", JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "estimator"),
)

# Cluster workers' ownership of partitions (roadgrip/cloud/cluster/worker.py): a worker that takes a partition raises its
# epoch; a write fenced with an older epoch fails (`Storage.write_batch`'s `fences`), so that a worker that lost a
# partition without noticing stores nothing of it after the next owner has begun.
partition_owners_table = Table(
    "partition_owners",
    metadata,
    Column("partition_id", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False),
)

# Cluster mode's friction map (roadgrip/cloud/cluster/regions.py): each cell's state as its region's owner last saved it
# (`FrictionMap.cell_states`), for the API replicas to render the map from and a new owner to go on from; the owners of
# region queues, with an epoch each, fence those writes and the region's warnings as partition_owners fence telemetry.
map_cells_table = Table(
    "map_cells",
    metadata,
    Column("cell", sa.String, primary_key=True),
    Column("region", sa.String, nullable=False),
    Column("last_ms", sa.BigInteger, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    Column("state", JSON, nullable=False),
    sa.Index("ix_map_cells_region", "region"),
    sa.Index("ix_map_cells_last_ms", "last_ms"),
)
region_owners_table = Table(
    "region_owners",
    metadata,
    Column("region_queue", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False),
)

# Counters shared by the processes of a cluster: the DENM ActionID sequence numbers of the regions' warning engines
# (one originating station, many engines).
counters_table = Table(
    "counters", metadata, Column("name", sa.String, primary_key=True), Column("value", sa.BigInteger, nullable=False)
)

# Roadside stations' reports (roadgrip/cloud/domain/stations.py), as validated, with the evidence the service drew from them.
station_reports_table = Table(
    "station_reports",
    metadata,
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
    Column("cells", JSON, nullable=False),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("station_id", "timestamp_ms"),
    sa.Index("ix_station_reports_timestamp_ms", "timestamp_ms"),
)

# Edge vehicles' friction observations and heartbeats (roadgrip/cloud/ingest/observations.py), as validated; an
# observation is one pass, keyed by its vehicle and its time (its last estimate's).
observations_table = Table(
    "observations",
    metadata,
    *(Column(c.name, _sql_type(c), nullable=not c.required) for c in OBSERVATION),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "last_ms"),
    sa.Index("ix_observations_last_ms", "last_ms"),
)
heartbeats_table = Table(
    "heartbeats",
    metadata,
    *(Column(c.name, _sql_type(c), nullable=not c.required) for c in HEARTBEAT),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "timestamp_ms"),
)
