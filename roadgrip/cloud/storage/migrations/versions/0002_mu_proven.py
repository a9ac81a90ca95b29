"""Add estimates.mu_proven.

estimates.mu_proven (what the car's own acceleration proves), added to an estimates table made before it; its
older rows hold null there.

Revision ID: 0002_mu_proven
Revises: 0001_tables
"""

import logging

import sqlalchemy as sa
from alembic import op

revision = "0002_mu_proven"
down_revision = "0001_tables"
branch_labels = None
depends_on = None

log = logging.getLogger("roadgrip.cloud.storage.migrations")


def upgrade() -> None:
    # the result's keys, not the inspector (which warns about PostGIS's geometry type it cannot reflect)
    columns = op.get_bind().execute(sa.text("SELECT * FROM estimates LIMIT 0")).keys()
    if "mu_proven" not in columns:
        op.add_column("estimates", sa.Column("mu_proven", sa.Float))
        log.info("added column estimates.mu_proven to a database of an older version")
