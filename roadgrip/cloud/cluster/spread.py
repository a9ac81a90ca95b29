"""Spreading single-active-consumer queues over the live workers: one rule for the partition queues
(roadgrip/cloud/cluster/worker.py) and the region queues (roadgrip/cloud/cluster/regions.py).

RabbitMQ 3.10 makes the first consumer registered on a queue its single active consumer (consumer priorities do not
choose it on a quorum queue there: docs/CLUSTER.md, "Workers"), so workers hand queues over themselves: a worker
releases the queue it took last (it stops taking deliveries, stores and acknowledges what it took, closes that
connection and registers again at the end of the queue's waiting list) when it holds more than its share:

- more than ceil(queues / live workers), or
- more than floor(queues / live workers) >= 1 while a live worker holds none and this one holds the most (ties: the
  smallest owner name, so that one worker of those holding the most moves).

Against flapping, nothing moves until the count of live workers has held for WORKERS_SETTLE_S, and a worker releases
at most one queue of a kind every `move_interval_s`. A queue released that comes back to the worker (no other live
worker took it) stops the moves until the count of live workers changes: with a count that holds, each worker moves
at most the queues above its share, once each. A queue taken less than FRESH_S ago is not released: the broker may
have handed it over from a worker that died, which the count shows only a lease later (and then no move is needed).
Each move is logged with its reason.

Who lives (`Liveness`): each worker raises its heartbeat counter in PostgreSQL every second or so
(roadgrip/cloud/storage/partitions.py); a worker is live while its counter has moved within WORKER_LEASE_S by the
reader's clock (one first seen counts as live for a lease). A worker killed stops raising it and is counted dead a
lease later; one stopped cleanly deletes it and is counted dead at once. The database, not the broker, keeps this
count: a dead RabbitMQ node leaves a queue's consumer count stale (its consumers are only suspected down: issue 25),
and a worker's heartbeat does not depend on which node it reaches.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

WORKERS_SETTLE_S = 5.0  # the live workers' count must hold this long before queues move
WORKER_LEASE_S = 10.0  # a worker whose heartbeat counter has not moved for this long is dead
FRESH_S = WORKER_LEASE_S + WORKERS_SETTLE_S  # a queue taken less than this ago stays where it is
DEAD_ROW_S = 300.0  # a heartbeat counter that has not moved for this long is deleted (by any worker that reads it)


class Liveness:
    """The live workers, from their heartbeat counters as read every second or so (module docstring)."""

    def __init__(self, lease_s: float = WORKER_LEASE_S):
        self.lease_s = lease_s
        self._moved: dict[str, tuple[int, float]] = {}  # owner -> (its counter, when it was last seen to move)

    def count(self, now: float, beats: Mapping[str, int]) -> int:
        """The live workers at `now` (monotonic s) given every worker's heartbeat counter as just read."""
        self._moved = {
            owner: seen if (seen := self._moved.get(owner)) is not None and seen[0] == n else (n, now)
            for owner, n in beats.items()
        }
        return sum(1 for _, moved in self._moved.values() if now - moved < self.lease_s)

    def dead_rows(self, now: float) -> dict[str, int]:
        """owner -> counter of the heartbeats that have not moved for DEAD_ROW_S (to delete, if still that value)."""
        return {owner: n for owner, (n, moved) in self._moved.items() if now - moved >= DEAD_ROW_S}


class Spread:
    """The spreading rule's state for one kind of queue in one worker. `release` is called every second or so by
    the worker's watcher thread; the caller does the release itself."""

    def __init__(self, queues: int, kind: str, owner: str, move_interval_s: float):
        self.queues = queues
        self.kind = kind  # "partition", "region queue": for the log
        self.owner = owner  # this worker's name in the owners' table
        self.move_interval_s = move_interval_s
        self.moves = 0  # queues released to spread them over the workers
        self._workers_seen: int | None = None  # the live workers' count as last seen ...
        self._workers_since = 0.0  # ... since then (monotonic s)
        self._next_move_at = 0.0
        self._released: set[int] = set()  # queues released since the count of live workers last changed
        self._stuck = False  # one of them came back: nothing moves until the count changes

    def release(
        self, now: float, workers: int | None, held: Mapping[int, float], owners: Callable[[], Mapping[int, str]]
    ) -> int | None:
        """The queue to release now, or None. `now`: monotonic s; `workers`: the live workers (None: not known);
        `held`: the queues this worker holds, each with when it took it (monotonic s); `owners`: reads every queue's
        owner (the database's owners table, read only when the second rule needs it; it may raise)."""
        if workers != self._workers_seen:
            self._workers_seen, self._workers_since = workers, now
            self._released, self._stuck = set(), False
            log.info("live workers: %s", workers)
        if not self._stuck and self._released & held.keys():
            self._stuck = True
            log.warning(
                "%s %s came back: no other live worker took it; nothing moves until the count of live workers changes",
                self.kind,
                sorted(self._released & held.keys()),
            )
        if self._stuck or not workers or now - self._workers_since < WORKERS_SETTLE_S or now < self._next_move_at:
            return None
        high, low = -(-self.queues // workers), self.queues // workers
        reason = None
        if len(held) > high:
            reason = (
                f"holds {len(held)} of {self.queues} {self.kind}s, more than ceil({self.queues} / {workers} live "
                f"workers) = {high}"
            )
        elif low >= 1 and len(held) > low:
            counts = collections.Counter(owners().values())
            idle = workers - len(counts)  # live workers holding none (fewer where a dead owner is still named)
            most = max(counts.values(), default=0)
            if (
                idle > 0
                and counts.get(self.owner) == most == len(held)
                and min(o for o, n in counts.items() if n == most) == self.owner
            ):
                reason = f"holds {len(held)}, the most, while {idle} of {workers} live workers hold none"
        if reason is None:
            return None
        queue = max(held, key=held.__getitem__)
        if now - held[queue] < FRESH_S:
            return None
        log.info("releasing %s %d: this worker %s", self.kind, queue, reason)
        self.moves += 1
        self._released.add(queue)
        self._next_move_at = now + self.move_interval_s
        return queue
