"""Alembic's environment for roadgrip's storage: run by roadgrip/cloud/storage/migrate.py (`open_storage`), which
passes the connection to migrate, with its transaction open, in the Config's attributes."""

from alembic import context

from roadgrip.cloud.storage.migrate import VERSION_TABLE, not_postgis
from roadgrip.cloud.storage.schema import metadata

connection = context.config.attributes.get("connection")
if connection is None:
    raise RuntimeError(
        "roadgrip's migrations run through roadgrip.cloud.storage.migrate.upgrade (open_storage), "
        "which passes the connection; there is no alembic.ini"
    )
context.configure(
    connection=connection, target_metadata=metadata, version_table=VERSION_TABLE, include_object=not_postgis
)
with context.begin_transaction():
    context.run_migrations()
