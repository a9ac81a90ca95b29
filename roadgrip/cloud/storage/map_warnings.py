"""Warnings and the friction map's cells: the warnings table (DENM-shaped warnings, by warning_id), and for cluster
mode the map_cells saved by each region's owner, the region_owners whose epochs fence those writes (as
partition_owners fence telemetry) and the counters table (the regions' DENM ActionID sequence numbers)."""

from __future__ import annotations

from sqlalchemy import select
from sqlalchemy.engine import Connection

from roadgrip.cloud.storage.base import Database, Fenced, checked_rows, now_ms
from roadgrip.cloud.storage.schema import counters_table, map_cells_table, region_owners_table, warnings_table

ACTIVE = "active"  # the warning status that `warnings(active_only=True)` selects
_WARNING_UPDATES = ("cell", "status", "detection_ms", "updated_ms", "message")  # what a stored warning takes anew


def _checked_warnings(rows: list[dict]) -> list[dict]:
    """The last row of each warning_id, checked (`checked_rows`); TypeError for a message that is not a dict."""
    latest = {}
    for row in rows:
        if not isinstance(row.get("message"), dict):
            raise TypeError(
                f"message of warning {row.get('warning_id')!r} must be a dict, got {type(row.get('message')).__name__}"
            )
        latest[row["warning_id"]] = row
    return checked_rows("warning", list(latest.values()), warnings_table)


def _check_region_fence(conn: Connection, fence: tuple[int, int] | None) -> None:
    """Read the epoch of the region queue of `fence` (region queue, the epoch `take_region_queue` gave the writer)
    under a share lock, held until `conn`'s transaction ends; Fenced if another owner has taken that queue since."""
    if fence is None:
        return
    c = region_owners_table.c
    epoch = conn.execute(select(c.epoch).where(c.region_queue == fence[0]).with_for_update(read=True)).scalar()
    if epoch != fence[1]:
        raise Fenced({fence[0]})


class MapWarnings:
    """Warnings, map cells, region owners and counters on one `Database` (the methods of `Storage` of the same
    names)."""

    def __init__(self, db: Database):
        self._db = db

    def _upsert_warnings(self, conn: Connection, rows: list[dict]) -> None:
        insert = self._db.insert(warnings_table)
        conn.execute(
            insert.on_conflict_do_update(
                index_elements=["warning_id"], set_={name: insert.excluded[name] for name in _WARNING_UPDATES}
            ),
            rows,
        )

    def put_warnings(self, rows: list[dict]) -> None:
        """Store (or replace) warnings in one transaction: each row holds warning_id, cell, status, detection_ms,
        updated_ms and message (a JSON-able dict, the DENM-shaped warning). Of rows with the same warning_id the last
        one wins."""
        rows = _checked_warnings(rows)
        if not rows:
            return
        with self._db.transaction() as conn:
            self._upsert_warnings(conn, rows)

    def put_region_output(self, warnings: list[dict], cells: list[dict], fence: tuple[int, int] | None = None) -> None:
        """Store a region's warnings (rows as `put_warnings` takes them) and map cells (cell, region, last_ms, state;
        updated_ms defaults to now; a stored cell is replaced) in one transaction. `fence` (region queue, the epoch
        `take_region_queue` gave the writer): read under a share lock first; Fenced, storing nothing, if another owner
        has taken that queue since."""
        warnings = _checked_warnings(warnings)
        updated_ms = now_ms()
        cells = checked_rows(
            "map cell",
            list({row["cell"]: {"updated_ms": updated_ms, **row} for row in cells}.values()),
            map_cells_table,
        )
        if not warnings and not cells:
            return
        with self._db.transaction() as conn:
            _check_region_fence(conn, fence)
            if warnings:
                self._upsert_warnings(conn, warnings)
            if cells:
                insert = self._db.insert(map_cells_table)
                conn.execute(
                    insert.on_conflict_do_update(
                        index_elements=["cell"],
                        set_={name: insert.excluded[name] for name in ("region", "last_ms", "updated_ms", "state")},
                    ),
                    cells,
                )

    def map_cells(self, region: str | None = None, since_ms: int | None = None) -> list[dict]:
        """Stored map cells (cell, region, last_ms, updated_ms, state), of one region or all, with last_ms >= since_ms
        when given, by cell."""
        c = map_cells_table.c
        query = select(map_cells_table).order_by(c.cell)
        if region is not None:
            query = query.where(c.region == region)
        if since_ms is not None:
            query = query.where(c.last_ms >= since_ms)
        return self._db.all(query)

    def delete_map_cells(self, region: str, before_ms: int, fence: tuple[int, int] | None = None) -> int:
        """Delete a region's map cells whose newest evidence is older than before_ms (fenced as `put_region_output`);
        how many."""
        c = map_cells_table.c
        with self._db.transaction() as conn:
            _check_region_fence(conn, fence)
            return conn.execute(map_cells_table.delete().where(c.region == region, c.last_ms < before_ms)).rowcount

    def next_action_sequence_number(self) -> int:
        """The next DENM ActionID sequence number of the cluster's warnings (0, 1, ... 65535, 0, ...), one atomic
        step of the counter `action_sequence_number`."""
        c = counters_table.c
        insert = self._db.insert(counters_table).values(name="action_sequence_number", value=0)
        upsert = insert.on_conflict_do_update(index_elements=["name"], set_={"value": (c.value + 1) % 65536})
        with self._db.transaction() as conn:
            return conn.execute(upsert.returning(c.value)).scalar_one()

    def region_owners(self) -> dict[int, str]:
        """region_queue -> the owner that took it last (region_owners)."""
        c = region_owners_table.c
        return {row["region_queue"]: row["owner"] for row in self._db.all(select(c.region_queue, c.owner))}

    def take_region_queue(self, region_queue: int, owner: str) -> int:
        """Raise the region queue's epoch (1 when first taken) and name `owner` as its owner; returns the new epoch,
        which the owner's fenced writes carry (`put_region_output`)."""
        insert = self._db.insert(region_owners_table).values(
            region_queue=region_queue, epoch=1, owner=owner, taken_ms=now_ms()
        )
        upsert = insert.on_conflict_do_update(
            index_elements=["region_queue"],
            set_={
                "epoch": region_owners_table.c.epoch + 1,
                "owner": insert.excluded.owner,
                "taken_ms": insert.excluded.taken_ms,
            },
        ).returning(region_owners_table.c.epoch)
        with self._db.transaction() as conn:
            return conn.execute(upsert).scalar_one()

    def warnings(self, active_only: bool = False) -> list[dict]:
        """All warnings (or only those whose status is "active"), by detection time."""
        c = warnings_table.c
        query = select(warnings_table).order_by(c.detection_ms, c.warning_id)
        return self._db.all(query.where(c.status == ACTIVE) if active_only else query)
