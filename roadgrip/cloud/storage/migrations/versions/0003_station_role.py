"""Widen the credentials' role check to the station role.

The credentials' role check widened to the station role: a database made before it has a check that names only
vehicle, reader and admin, and would refuse a station's credential. PostgreSQL: the constraint replaced; SQLite,
which cannot alter a constraint: the table rebuilt and its rows copied (in migrate.py's one transaction).

Revision ID: 0003_station_role
Revises: 0002_mu_proven
"""

import logging

import sqlalchemy as sa
from alembic import op
from sqlalchemy import Column, Table

revision = "0003_station_role"
down_revision = "0002_mu_proven"
branch_labels = None
depends_on = None

log = logging.getLogger("roadgrip.cloud.storage.migrations")

ROLES = ("vehicle", "reader", "admin", "station")
credentials = Table(
    "credentials",
    sa.MetaData(),
    Column("name", sa.String, primary_key=True),
    Column("role", sa.String, sa.CheckConstraint(f"role IN {ROLES}", name="ck_credentials_role"), nullable=False),
    Column("secret_hash", sa.String, nullable=False),
    Column("vehicle_id", sa.String),
    Column("revoked", sa.Boolean, nullable=False),
    Column("created_ms", sa.BigInteger, nullable=False),
)


def upgrade() -> None:
    conn = op.get_bind()
    if conn.dialect.name == "postgresql":
        definition = conn.execute(
            sa.text("SELECT pg_get_constraintdef(oid) FROM pg_constraint WHERE conname = 'ck_credentials_role'")
        ).scalar()
        if definition is not None and "'station'" not in definition:
            op.drop_constraint("ck_credentials_role", "credentials", type_="check")
            op.create_check_constraint("ck_credentials_role", "credentials", f"role IN {ROLES}")
            log.info("credentials: role check widened to %s", ROLES)
        return
    definition = conn.execute(sa.text("SELECT sql FROM sqlite_master WHERE type = 'table' AND name = 'credentials'"))
    if "'station'" in definition.scalar():
        return
    op.rename_table("credentials", "credentials_before_stations")
    credentials.create(conn)
    columns = ", ".join(c.name for c in credentials.columns)
    conn.execute(sa.text(f"INSERT INTO credentials ({columns}) SELECT {columns} FROM credentials_before_stations"))
    op.drop_table("credentials_before_stations")
    log.info("credentials: table rebuilt with the role check of %s", ROLES)
