"""The observations and heartbeats tables: edge vehicles' friction observations and heartbeats (CONTRACTS 3.7,
roadgrip/cloud/ingest/observations.py), as validated. A repeat of a stored one (same key) is skipped: an edge vehicle
sends again what it has no PUBACK for (roadgrip/edge/uplink.py), and it is stored once. `put_edge` stores a batch of
both kinds in one transaction (serve's MQTT intake, roadgrip/cloud/serve/edge_intake.py)."""

from __future__ import annotations

from sqlalchemy import func, select

from roadgrip.cloud.storage.base import Database, check_limit, checked_rows, now_ms
from roadgrip.cloud.storage.schema import heartbeats_table, observations_table


class Observations:
    """Observations and heartbeats on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def put_edge(self, observations: list[dict], heartbeats: list[dict]) -> tuple[set[tuple[str, int]], int]:
        """Store observations and heartbeats in one transaction (received_ms defaults to now): a batch of edge
        messages. A row whose key is stored already, or came earlier in the same call, is skipped. The observation
        keys (vehicle_id, last_ms) newly stored, and how many heartbeats were new."""
        received_ms = now_ms()
        observations = checked_rows(
            "observation", [{"received_ms": received_ms, **row} for row in observations], observations_table
        )
        heartbeats = checked_rows(
            "heartbeat", [{"received_ms": received_ms, **row} for row in heartbeats], heartbeats_table
        )
        new, beats = set(), 0
        if not observations and not heartbeats:
            return new, beats
        o, h = observations_table.c, heartbeats_table.c
        with self._db.transaction() as conn:
            if observations:
                insert = self._db.insert(observations_table).on_conflict_do_nothing().returning(o.vehicle_id, o.last_ms)
                new = {(row[0], row[1]) for row in conn.execute(insert, observations)}
            if heartbeats:
                insert = self._db.insert(heartbeats_table).on_conflict_do_nothing().returning(h.vehicle_id)
                beats = len(conn.execute(insert, heartbeats).all())
        return new, beats

    def put_observations(self, rows: list[dict]) -> set[tuple[str, int]]:
        """Store observations in one transaction (put_edge); the keys newly stored."""
        return self.put_edge(rows, [])[0]

    def observations_since(self, since_ms: int, limit: int = 1_000_000) -> list[dict]:
        """The observations with last_ms >= since_ms, oldest first, at most `limit`."""
        check_limit(limit)
        c = observations_table.c
        query = select(observations_table).where(c.last_ms >= since_ms).order_by(c.last_ms, c.vehicle_id)
        return [_observation(row) for row in self._db.all(query.limit(limit))]

    def observation_extent(self) -> dict[str, tuple[int, int, int]]:
        """vehicle_id -> (rows, first last_ms, last last_ms) of its stored observations."""
        c = observations_table.c
        query = select(
            c.vehicle_id, func.count().label("n"), func.min(c.last_ms).label("first"), func.max(c.last_ms).label("last")
        )
        rows = self._db.all(query.group_by(c.vehicle_id))
        return {row["vehicle_id"]: (row["n"], row["first"], row["last"]) for row in rows}

    def put_heartbeats(self, rows: list[dict]) -> int:
        """Store heartbeats in one transaction (put_edge), repeats skipped; how many were new."""
        return self.put_edge([], rows)[1]

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
