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
at most one queue of a kind every `move_interval_s`. Each move is logged with its reason.
"""

from __future__ import annotations

import collections
import logging
from collections.abc import Callable, Mapping

log = logging.getLogger(__name__)

WORKERS_SETTLE_S = 5.0  # the live workers' count must hold this long before queues move


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

    def release(
        self, now: float, workers: int | None, held: Mapping[int, float], owners: Callable[[], Mapping[int, str]]
    ) -> int | None:
        """The queue to release now, or None. `now`: monotonic s; `workers`: the live workers (None: not known);
        `held`: the queues this worker holds, each with when it took it (monotonic s); `owners`: reads every queue's
        owner (the database's owners table, read only when the second rule needs it; it may raise)."""
        if workers != self._workers_seen:
            self._workers_seen, self._workers_since = workers, now
            log.info("live workers: %s", workers)
        if not workers or now - self._workers_since < WORKERS_SETTLE_S or now < self._next_move_at:
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
        log.info("releasing %s %d: this worker %s", self.kind, queue, reason)
        self.moves += 1
        self._next_move_at = now + self.move_interval_s
        return queue
