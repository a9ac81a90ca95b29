"""The observations and heartbeats tables: edge vehicles' friction observations and heartbeats (CONTRACTS 3.7,
roadgrip/cloud/ingest/observations.py), as validated. A repeat of a stored one (same key) is skipped: an edge vehicle
sends again what it has no PUBACK for (roadgrip/edge/uplink.py), and it is stored once."""

from __future__ import annotations

from sqlalchemy import func, select

from roadgrip.cloud.storage.base import Database, check_limit, checked_rows, now_ms
from roadgrip.cloud.storage.schema import heartbeats_table, observations_table


class Observations:
    """Observations and heartbeats on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def put_observations(self, rows: list[dict]) -> set[tuple[str, int]]:
        """Store observations in one transaction (received_ms defaults to now); those whose (vehicle_id, last_ms) is
        stored already are skipped. The keys newly stored."""
        received_ms = now_ms()
        rows = checked_rows("observation", [{"received_ms": received_ms, **row} for row in rows], observations_table)
        if not rows:
            return set()
        c = observations_table.c
        insert = self._db.insert(observations_table).on_conflict_do_nothing().returning(c.vehicle_id, c.last_ms)
        with self._db.transaction() as conn:
            return {(row[0], row[1]) for row in conn.execute(insert, rows)}

    def observations_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        """The observations with last_ms >= since_ms, oldest first, at most `limit`."""
        check_limit(limit)
        c = observations_table.c
        query = select(observations_table).where(c.last_ms >= since_ms).order_by(c.last_ms, c.vehicle_id)
        return [_observation(row) for row in self._db.all(query.limit(limit))]

    def put_heartbeats(self, rows: list[dict]) -> int:
        """Store heartbeats in one transaction, repeats skipped; how many were new."""
        received_ms = now_ms()
        rows = checked_rows("heartbeat", [{"received_ms": received_ms, **row} for row in rows], heartbeats_table)
        if not rows:
            return 0
        c = heartbeats_table.c
        insert = self._db.insert(heartbeats_table).on_conflict_do_nothing().returning(c.vehicle_id)
        with self._db.transaction() as conn:
            return len(conn.execute(insert, rows).all())

    def latest_heartbeats(self) -> list[dict]:
        """The newest heartbeat of every edge vehicle, by vehicle_id."""
        c = heartbeats_table.c
        newest = select(c.vehicle_id, func.max(c.timestamp_ms).label("t")).group_by(c.vehicle_id).subquery()
        query = select(heartbeats_table).join(
            newest, (c.vehicle_id == newest.c.vehicle_id) & (c.timestamp_ms == newest.c.t)
        )
        return self._db.all(query.order_by(c.vehicle_id))


def _observation(row: dict) -> dict:
    row.pop("received_ms")
    return row
