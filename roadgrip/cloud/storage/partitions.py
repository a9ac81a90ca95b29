"""Partition fencing (cluster mode, roadgrip/cloud/cluster/worker.py): the partition_owners table, whose epoch a
worker raises when it takes a partition (`take_partition`), and `check_fences`, which a fenced write runs first in its
transaction (telemetry and estimates, estimator states), so that a worker that lost a partition without noticing
stores nothing of it after the next owner has begun; and the workers' heartbeats, which tell which workers live
(roadgrip/cloud/cluster/spread.py `Liveness`): a counter per worker in the counters table, named HEARTBEAT_PREFIX +
the worker's owner name, that the worker raises about once a second and deletes at its clean stop. A counter, not a
time: a reader judges it by its own clock (has it moved lately?), so no two machines' clocks are compared."""

from __future__ import annotations

from collections.abc import Mapping

from sqlalchemy import select
from sqlalchemy.engine import Connection

from roadgrip.cloud.storage.base import Database, Fenced, now_ms
from roadgrip.cloud.storage.schema import counters_table, partition_owners_table

HEARTBEAT_PREFIX = "worker:"  # a worker's heartbeat counter: this, then its owner name


def check_fences(conn: Connection, fences: Mapping[int, int] | None) -> None:
    """Read the epochs of the partitions in `fences` (partition -> the epoch `take_partition` gave the writer) under
    a share lock, held until `conn`'s transaction ends; Fenced if another worker has taken one since."""
    if not fences:
        return
    c = partition_owners_table.c
    query = select(c.partition_id, c.epoch).where(c.partition_id.in_(sorted(fences))).with_for_update(read=True)
    epochs = dict(conn.execute(query).all())
    stale = {p for p, epoch in fences.items() if epochs.get(p) != epoch}
    if stale:
        raise Fenced(stale)


class Partitions:
    """The owners of partitions on one `Database` (the methods of `Storage` of the same names)."""

    def __init__(self, db: Database):
        self._db = db

    def take_partition(self, partition_id: int, owner: str) -> int:
        """Raise the partition's epoch (1 when first taken) and name `owner` as its owner; returns the new epoch,
        which the owner's fenced writes carry (`write_batch`). Waits for fenced writes of the partition in progress."""
        insert = self._db.insert(partition_owners_table).values(
            partition_id=partition_id, epoch=1, owner=owner, taken_ms=now_ms()
        )
        upsert = insert.on_conflict_do_update(
            index_elements=["partition_id"],
            set_={
                "epoch": partition_owners_table.c.epoch + 1,
                "owner": insert.excluded.owner,
                "taken_ms": insert.excluded.taken_ms,
            },
        ).returning(partition_owners_table.c.epoch)
        with self._db.transaction() as conn:
            return conn.execute(upsert).scalar_one()

    def partition_owners(self) -> dict[int, str]:
        """partition -> the owner that took it last (`take_partition`), for the partitions taken at least once."""
        c = partition_owners_table.c
        return {row["partition_id"]: row["owner"] for row in self._db.all(select(c.partition_id, c.owner))}

    def heartbeat(self, owner: str) -> None:
        """Raise the owner's heartbeat counter by one (0 when it has none)."""
        c = counters_table.c
        insert = self._db.insert(counters_table).values(name=HEARTBEAT_PREFIX + owner, value=0)
        with self._db.transaction() as conn:
            conn.execute(insert.on_conflict_do_update(index_elements=["name"], set_={"value": c.value + 1}))

    def worker_heartbeats(self) -> dict[str, int]:
        """owner -> its heartbeat counter, for every worker that has one."""
        c = counters_table.c
        rows = self._db.all(select(c.name, c.value).where(c.name.startswith(HEARTBEAT_PREFIX, autoescape=True)))
        return {row["name"][len(HEARTBEAT_PREFIX) :]: row["value"] for row in rows}

    def end_heartbeat(self, owner: str, beats: int | None = None) -> None:
        """Delete the owner's heartbeat counter (at its clean stop), or, with `beats`, only if it still holds that
        value (a dead worker's, deleted by another: a worker that beat since keeps it)."""
        c = counters_table.c
        query = counters_table.delete().where(c.name == HEARTBEAT_PREFIX + owner)
        if beats is not None:
            query = query.where(c.value == beats)
        with self._db.transaction() as conn:
            conn.execute(query)
