"""Create the tables a database lacks.

The tables, as roadgrip made them when it took up Alembic: each one a database lacks is created with its indexes
(all of them in a new database; in one from before the migrations, those that came after it). Frozen here, not
imported from schema.py, so that this revision does the same whatever schema.py later becomes.

Revision ID: 0001_tables
Revises: (none)
"""

import sqlalchemy as sa
from alembic import op
from sqlalchemy import Column, Table
from sqlalchemy.dialects import postgresql

revision = "0001_tables"
down_revision = None
branch_labels = None
depends_on = None

ROLES = ("vehicle", "reader", "admin", "station")
KEY = ("vehicle_id", "timestamp_ms")
JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
metadata = sa.MetaData()
Table(
    "telemetry",
    metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("timestamp_ms", sa.BigInteger, nullable=False),
    Column("latitude_deg", sa.Float),
    Column("longitude_deg", sa.Float),
    Column("speed_mps", sa.Float, nullable=False),
    Column("accel_lon_mps2", sa.Float, nullable=False),
    Column("accel_lat_mps2", sa.Float, nullable=False),
    Column("yaw_rate_radps", sa.Float, nullable=False),
    Column("steering_wheel_angle_rad", sa.Float, nullable=False),
    *(Column(f"wheel_speed_{w}_radps", sa.Float, nullable=False) for w in ("fl", "fr", "rl", "rr")),
    Column("abs_active", sa.Boolean, nullable=False),
    Column("acc_active", sa.Boolean, nullable=False),
    Column("tcs_active", sa.Boolean),
    Column("esc_active", sa.Boolean),
    Column("lateral_speed_mps", sa.Float),
    sa.PrimaryKeyConstraint(*KEY),
)
Table(
    "estimates",
    metadata,
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
    sa.PrimaryKeyConstraint(*KEY),
    sa.Index("ix_estimates_timestamp_ms", "timestamp_ms"),
)
Table(
    "vehicles",
    metadata,
    Column("vehicle_id", sa.String, primary_key=True),
    Column("profile", JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
)
Table(
    "credentials",
    metadata,
    Column("name", sa.String, primary_key=True),
    Column("role", sa.String, sa.CheckConstraint(f"role IN {ROLES}", name="ck_credentials_role"), nullable=False),
    Column("secret_hash", sa.String, nullable=False),
    Column("vehicle_id", sa.String),
    Column("revoked", sa.Boolean, nullable=False),
    Column("created_ms", sa.BigInteger, nullable=False),
)
Table(
    "warnings",
    metadata,
    Column("warning_id", sa.String, primary_key=True),
    Column("cell", sa.String, nullable=False),
    Column("status", sa.String, nullable=False),
    Column("detection_ms", sa.BigInteger, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    Column("message", JSON, nullable=False),
)
Table(
    "estimator_states",
    metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("estimator", sa.String, nullable=False),
    Column("state", JSON, nullable=False),
    Column("updated_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "estimator"),
)
Table(
    "partition_owners",
    metadata,
    Column("partition_id", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False),
)
Table(
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
Table(
    "region_owners",
    metadata,
    Column("region_queue", sa.Integer, primary_key=True, autoincrement=False),
    Column("epoch", sa.BigInteger, nullable=False),
    Column("owner", sa.String, nullable=False),
    Column("taken_ms", sa.BigInteger, nullable=False),
)
Table("counters", metadata, Column("name", sa.String, primary_key=True), Column("value", sa.BigInteger, nullable=False))
Table(
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


def upgrade() -> None:
    metadata.create_all(op.get_bind(), checkfirst=True)
