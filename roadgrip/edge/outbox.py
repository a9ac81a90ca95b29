"""The vehicle's disk-backed outbox (SQLite): every message the agent makes waits here until the broker has
acknowledged it (MQTT QoS 1 PUBACK, roadgrip/edge/uplink.py), so that nothing is lost across a coverage gap, a broker
restart or a kill of the agent (kill -9: the rows are committed before `put` returns; synchronous=FULL, so a power
cut loses nothing committed either).

The limit: at most `limit_messages` (default LIMIT_MESSAGES, 100,000) wait at once. A message put while the outbox is
full pushes out the oldest waiting one: it is deleted, counted (`dropped`, kept in the file, sent in every heartbeat)
and logged. Oldest-dropped because the map ages evidence (a pass weighs 2^(-age / 600 s) and counts no more after
an hour, roadgrip/cloud/domain/friction_map.py): when the outbox overflows, the newest observations are the ones
that still matter, and a car must keep making them. At the agent's rate on the fleet benchmark's drives (docs/EDGE.md)
the default holds days of driving out of coverage in a few tens of MB of disk.

Thread-safe (one connection under a lock): the agent puts from its loop, the uplink removes from paho's thread.
"""

from __future__ import annotations

import logging
import sqlite3
import threading
import time
from pathlib import Path

log = logging.getLogger(__name__)

LIMIT_MESSAGES = 100_000

_SCHEMA = (
    (
        "CREATE TABLE IF NOT EXISTS outbox (id INTEGER PRIMARY KEY AUTOINCREMENT, topic TEXT NOT NULL, "
        "payload BLOB NOT NULL, created_ms INTEGER NOT NULL)"
    ),
    "CREATE TABLE IF NOT EXISTS counters (name TEXT PRIMARY KEY, value INTEGER NOT NULL)",
)


class Outbox:
    """Messages (topic, payload) waiting for their PUBACK, oldest first, in an SQLite file (module docstring)."""

    def __init__(self, path: str | Path, limit_messages: int = LIMIT_MESSAGES):
        if isinstance(limit_messages, bool) or not isinstance(limit_messages, int) or limit_messages < 1:
            raise ValueError(f"outbox limit_messages must be an integer >= 1, got {limit_messages!r}")
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self.limit_messages = limit_messages
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.path, check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.execute("PRAGMA synchronous=FULL")
        for statement in _SCHEMA:
            self._db.execute(statement)
        self._pending = self._db.execute("SELECT COUNT(*) FROM outbox").fetchone()[0]
        row = self._db.execute("SELECT value FROM counters WHERE name = 'dropped'").fetchone()
        self._dropped = row[0] if row else 0

    @property
    def pending(self) -> int:
        """Messages waiting."""
        return self._pending

    @property
    def dropped(self) -> int:
        """Messages pushed out at the limit since the file was made."""
        return self._dropped

    def put(self, topic: str, payload: bytes, now_ms: int | None = None) -> int:
        """Keep a message until `remove`d (durable when this returns); its id. At the limit the oldest is dropped."""
        created = int(time.time() * 1000) if now_ms is None else now_ms
        with self._lock:
            self._db.execute("BEGIN IMMEDIATE")
            try:
                over = self._pending + 1 - self.limit_messages
                if over > 0:
                    self._db.execute(
                        "DELETE FROM outbox WHERE id IN (SELECT id FROM outbox ORDER BY id LIMIT ?)", (over,)
                    )
                    self._dropped += over
                    self._db.execute(
                        "INSERT INTO counters (name, value) VALUES ('dropped', ?) "
                        "ON CONFLICT (name) DO UPDATE SET value = excluded.value",
                        (self._dropped,),
                    )
                    self._pending -= over
                cursor = self._db.execute(
                    "INSERT INTO outbox (topic, payload, created_ms) VALUES (?, ?, ?)", (topic, payload, created)
                )
                self._db.execute("COMMIT")
            except BaseException:
                self._db.execute("ROLLBACK")
                raise
            self._pending += 1
        if over > 0 and (self._dropped == over or self._dropped % 1000 < over):  # the first drop, then every 1,000th
            log.warning(
                "outbox %s full (%d messages): dropped the oldest, %d so far",
                self.path,
                self.limit_messages,
                self._dropped,
            )
        return cursor.lastrowid

    def oldest(self, n: int, after_id: int = 0) -> list[tuple[int, str, bytes]]:
        """Up to `n` waiting messages (id, topic, payload) with an id above `after_id`, oldest first."""
        with self._lock:
            return self._db.execute(
                "SELECT id, topic, payload FROM outbox WHERE id > ? ORDER BY id LIMIT ?", (after_id, n)
            ).fetchall()

    def remove(self, message_id: int) -> bool:
        """Forget an acknowledged message; False when it was not waiting (removed already, or dropped)."""
        with self._lock:
            removed = self._db.execute("DELETE FROM outbox WHERE id = ?", (message_id,)).rowcount
            self._pending -= removed
        return bool(removed)

    def close(self) -> None:
        with self._lock:
            self._db.close()
