"""The credentials table: who may log in (vehicles, readers, admins, stations) and with which secret's hash."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from sqlalchemy import select

from roadgrip.cloud.storage.base import Database, now_ms
from roadgrip.cloud.storage.schema import ROLES, credentials_table


@dataclass(frozen=True)
class Credential:
    name: str  # login name: a vehicle's id for vehicles, a free name for readers and admins
    role: str  # one of ROLES
    secret_hash: str
    vehicle_id: str | None  # the vehicle a "vehicle" credential speaks for; None for the other roles
    revoked: bool
    created_ms: int


class Credentials:
    """Credentials on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def add_credential(
        self,
        name: str,
        role: str,
        secret_hash: str,
        vehicle_id: str | None = None,
        before_commit: Callable[[], None] | None = None,
    ) -> None:
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
                raise ValueError(
                    f"a vehicle credential is named by its vehicle's id: name {name!r}, vehicle_id {vehicle_id!r}"
                )
        elif vehicle_id is not None:
            raise ValueError(f"a {role} credential has no vehicle_id, got {vehicle_id!r}")
        row = {
            "name": name,
            "role": role,
            "secret_hash": secret_hash,
            "vehicle_id": vehicle_id,
            "revoked": False,
            "created_ms": now_ms(),
        }
        insert = self._db.insert(credentials_table).values(row).on_conflict_do_nothing()
        with self._db.transaction() as conn:
            added = conn.execute(insert.returning(credentials_table.c.name)).first()
            if added is None:
                raise ValueError(f"a credential named {name!r} exists already")
            if before_commit is not None:
                before_commit()

    def credential(self, name: str) -> Credential | None:
        rows = self._db.all(select(credentials_table).where(credentials_table.c.name == name))
        return Credential(**rows[0]) if rows else None

    def credentials(self) -> list[Credential]:
        return [Credential(**row) for row in self._db.all(select(credentials_table).order_by(credentials_table.c.name))]

    def revoke_credential(self, name: str) -> bool:
        """Revoke credential `name`; True if it existed and was active."""
        c = credentials_table.c
        with self._db.transaction() as conn:
            query = credentials_table.update().where(c.name == name, c.revoked.is_(False)).values(revoked=True)
            return conn.execute(query).rowcount == 1

    def set_secret_hash(self, name: str, secret_hash: str) -> None:
        """Replace credential `name`'s secret hash (revoked or not); ValueError if there is no such credential."""
        with self._db.transaction() as conn:
            query = credentials_table.update().where(credentials_table.c.name == name)
            if conn.execute(query.values(secret_hash=secret_hash)).rowcount != 1:
                raise ValueError(f"no credential named {name!r}")
