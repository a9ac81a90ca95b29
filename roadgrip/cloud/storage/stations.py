"""The station_reports table: roadside stations' reports (roadgrip/cloud/domain/stations.py) as validated, with the
evidence the service drew from them."""

from __future__ import annotations

from collections.abc import Iterable

import sqlalchemy as sa
from sqlalchemy import func, select

from roadgrip.cloud.storage.base import Database, check_limit, checked_rows, now_ms
from roadgrip.cloud.storage.schema import station_reports_table


class StationReports:
    """Station reports on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def put_station_reports(self, rows: list[dict]) -> set[tuple[str, int]]:
        """Store station reports in one transaction (keys: the station_reports table's columns; received_ms defaults
        to now); a report whose (station_id, timestamp_ms) is stored already is skipped. Returns the keys newly
        stored."""
        received_ms = now_ms()
        rows = checked_rows(
            "station report", [{"received_ms": received_ms, **row} for row in rows], station_reports_table
        )
        if not rows:
            return set()
        c = station_reports_table.c
        insert = self._db.insert(station_reports_table).on_conflict_do_nothing().returning(c.station_id, c.timestamp_ms)
        with self._db.transaction() as conn:
            return {(row[0], row[1]) for row in conn.execute(insert, rows)}

    def latest_station_reports(self) -> list[dict]:
        """The newest report of every station, by station_id."""
        c = station_reports_table.c
        newest = select(c.station_id, func.max(c.timestamp_ms)).group_by(c.station_id)
        query = select(station_reports_table).where(sa.tuple_(c.station_id, c.timestamp_ms).in_(newest))
        return self._db.all(query.order_by(c.station_id))

    def station_reports_of(self, keys: Iterable[tuple[str, int]]) -> list[dict]:
        """The stored reports with these keys (station_id, timestamp_ms), oldest first; keys not stored are left out."""
        keys = sorted(set(keys))
        if not keys:
            return []
        c = station_reports_table.c
        return self._db.all(
            select(station_reports_table)
            .where(sa.tuple_(c.station_id, c.timestamp_ms).in_(keys))
            .order_by(c.timestamp_ms, c.station_id)
        )

    def station_reports_since(self, since_ms: int, limit: int = 100_000) -> list[dict]:
        """The reports of all stations with timestamp_ms >= since_ms, oldest first, at most `limit`."""
        check_limit(limit)
        c = station_reports_table.c
        return self._db.all(
            select(station_reports_table)
            .where(c.timestamp_ms >= since_ms)
            .order_by(c.timestamp_ms, c.station_id)
            .limit(limit)
        )
