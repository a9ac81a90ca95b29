"""The vehicles table (each vehicle's profile, CONTRACTS 3.2), and registering a fleet: profiles and their "vehicle"
credentials in one transaction."""

from __future__ import annotations

from collections import Counter
from collections.abc import Callable

from sqlalchemy import select

from roadgrip.cloud.storage.base import Database, now_ms
from roadgrip.cloud.storage.schema import credentials_table, vehicles_table


class Vehicles:
    """Vehicle profiles on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def put_vehicle(self, vehicle_id: str, profile: dict) -> None:
        """Store (or replace) the profile of `vehicle_id`: a JSON-able dict of CONTRACTS 3.2 fields."""
        if not isinstance(profile, dict):
            raise TypeError(f"profile of vehicle {vehicle_id!r} must be a dict, got {type(profile).__name__}")
        with self._db.transaction() as conn:
            conn.execute(self._profile_upsert(), {"vehicle_id": vehicle_id, "profile": profile, "updated_ms": now_ms()})

    def _profile_upsert(self):
        """INSERT of vehicle profiles that replaces a stored one (parameters: vehicle_id, profile, updated_ms)."""
        insert = self._db.insert(vehicles_table)
        return insert.on_conflict_do_update(
            index_elements=["vehicle_id"],
            set_={"profile": insert.excluded.profile, "updated_ms": insert.excluded.updated_ms},
        )

    def register_vehicles(
        self, vehicles: list[tuple[str, dict, str]], before_commit: Callable[[], None] | None = None
    ) -> None:
        """For each (vehicle_id, profile, secret_hash): store the profile (replacing a stored one) and a new "vehicle"
        credential named vehicle_id, all in one transaction, so that a failure part way leaves none of them stored
        (nor a credential whose secret nobody received). ValueError, storing nothing, when a vehicle_id is given twice
        or its credential name is taken. `before_commit` runs once every row is in, before the commit (the cluster
        creates the vehicles' broker users there: roadgrip/cloud/cluster/api_backend.py); what it raises rolls it all
        back."""
        ids = [vehicle_id for vehicle_id, _, _ in vehicles]
        twice = sorted(v for v, n in Counter(ids).items() if n > 1)
        if twice:
            raise ValueError(f"vehicle_id(s) given twice: {', '.join(twice[:10])}")
        for vehicle_id, profile, _ in vehicles:
            if not isinstance(profile, dict):
                raise TypeError(f"profile of vehicle {vehicle_id!r} must be a dict, got {type(profile).__name__}")
        if not vehicles:
            return
        created_ms = now_ms()
        credentials = self._db.insert(credentials_table).on_conflict_do_nothing().returning(credentials_table.c.name)
        with self._db.transaction() as conn:
            added = {
                row[0]
                for row in conn.execute(
                    credentials,
                    [
                        {
                            "name": v,
                            "role": "vehicle",
                            "secret_hash": h,
                            "vehicle_id": v,
                            "revoked": False,
                            "created_ms": created_ms,
                        }
                        for v, _, h in vehicles
                    ],
                )
            }
            if len(added) < len(vehicles):  # raising rolls the transaction back
                taken = [v for v in ids if v not in added]
                raise ValueError(f"vehicle_id(s) already registered: {', '.join(taken[:10])}")
            conn.execute(
                self._profile_upsert(),
                [{"vehicle_id": v, "profile": p, "updated_ms": created_ms} for v, p, _ in vehicles],
            )
            if before_commit is not None:
                before_commit()

    def vehicle_profile(self, vehicle_id: str) -> dict | None:
        return self._db.scalar(select(vehicles_table.c.profile).where(vehicles_table.c.vehicle_id == vehicle_id))

    def vehicle_ids(self) -> list[str]:
        """The ids of the vehicles with a stored profile, sorted."""
        return [
            row["vehicle_id"]
            for row in self._db.all(select(vehicles_table.c.vehicle_id).order_by(vehicles_table.c.vehicle_id))
        ]
