"""Add the observations and heartbeats tables (edge vehicles, CONTRACTS 3.7).

Frozen here, not imported from schema.py, so that this revision does the same whatever schema.py later becomes.

Revision ID: 0005_observations
Revises: 0004_optional_channels
"""

import logging

import sqlalchemy as sa
from alembic import op
from sqlalchemy import Column, Table
from sqlalchemy.dialects import postgresql

revision = "0005_observations"
down_revision = "0004_optional_channels"
branch_labels = None
depends_on = None

log = logging.getLogger("roadgrip.cloud.storage.migrations")

JSON = sa.JSON().with_variant(postgresql.JSONB(), "postgresql")
metadata = sa.MetaData()
observations = Table(
    "observations",
    metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("h3_cell", sa.String, nullable=False),
    Column("first_ms", sa.BigInteger, nullable=False),
    Column("last_ms", sa.BigInteger, nullable=False),
    Column("latitude_deg", sa.Float, nullable=False),
    Column("longitude_deg", sa.Float, nullable=False),
    Column("mu", sa.Float, nullable=False),
    Column("mu_lower", sa.Float, nullable=False),
    Column("mu_upper", sa.Float, nullable=False),
    Column("mu_proven", sa.Float),
    Column("excited", sa.Boolean, nullable=False),
    Column("n_estimates", sa.BigInteger, nullable=False),
    Column("n_excited", sa.BigInteger, nullable=False),
    Column("evidence", JSON, nullable=False),
    Column("channels", JSON, nullable=False),
    Column("vehicle_class", sa.String, nullable=False),
    Column("estimator", sa.String, nullable=False),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "last_ms"),
    sa.Index("ix_observations_last_ms", "last_ms"),
)
heartbeats = Table(
    "heartbeats",
    metadata,
    Column("vehicle_id", sa.String, nullable=False),
    Column("timestamp_ms", sa.BigInteger, nullable=False),
    Column("latitude_deg", sa.Float),
    Column("longitude_deg", sa.Float),
    Column("n_samples", sa.BigInteger, nullable=False),
    Column("n_observations", sa.BigInteger, nullable=False),
    Column("outbox_pending", sa.BigInteger, nullable=False),
    Column("outbox_dropped", sa.BigInteger, nullable=False),
    Column("received_ms", sa.BigInteger, nullable=False),
    sa.PrimaryKeyConstraint("vehicle_id", "timestamp_ms"),
)


def upgrade() -> None:
    conn = op.get_bind()
    existing = set(sa.inspect(conn).get_table_names())
    for table in (observations, heartbeats):
        if table.name not in existing:
            table.create(conn)
            log.info("created table %s", table.name)
