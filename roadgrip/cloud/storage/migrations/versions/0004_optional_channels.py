"""Add the optional channels to telemetry.

The optional channels of wire format v1 (CONTRACTS 3.1: GNSS speed and its accuracy, drive and brake force, the
driver's and the EPS's steering torque), added to a telemetry table made before them; its older rows hold null there
(not sent). Frozen here, not imported from schema.py.

Revision ID: 0004_optional_channels
Revises: 0003_station_role
"""

import logging

import sqlalchemy as sa
from alembic import op

revision = "0004_optional_channels"
down_revision = "0003_station_role"
branch_labels = None
depends_on = None

CHANNELS = (
    "gnss_speed_mps",
    "gnss_speed_accuracy_mps",
    "drive_force_n",
    "brake_force_n",
    "steering_torque_nm",
    "eps_assist_torque_nm",
)
log = logging.getLogger("roadgrip.cloud.storage.migrations")


def upgrade() -> None:
    columns = op.get_bind().execute(sa.text("SELECT * FROM telemetry LIMIT 0")).keys()
    for name in CHANNELS:
        if name not in columns:
            op.add_column("telemetry", sa.Column(name, sa.Float))
            log.info("added column telemetry.%s to a database of an older version", name)
