"""Replaying recorded telemetry: a log's wire-format samples sent again at the pace they were recorded.

`replay_file(path)` imports a log with the importer that recognises it (or the one named: roadgrip.fleet.importers)
and returns its samples as wire-format v1 dicts (CONTRACTS 3.1). `replay(samples, send)` hands them to `send` in time
order, in batches, at `speed` times real time. Sending stays abstract: `send` is any callable taking a list of
samples (an HTTP POST, an MQTT publish, a list's append in a test).

Pacing. The samples are ordered by timestamp_ms (stable: equal timestamps keep their order). Sample i is due
(ts_i - ts_0) / 1000 / speed seconds after the replay starts, on `clock.monotonic()`. A batch goes out when its last
sample is due (a terminal cannot send what it has not yet measured) and holds up to `batch` samples of one vehicle
(a terminal sends only its own, under its own credentials and topic): with several vehicles, each fills its own batch,
and what is left goes out when that vehicle's last sample is due. The schedule is absolute, so a slow `send` delays
the batches after it without adding up drift; a batch sent after its time counts as late. speed 0 or infinity:
no waiting at all.

The samples are passed on as they are: replay rewrites no field (not even the timestamps: shift them on import with
`start_ms`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from roadgrip.fleet.importers import Importer, resolve_importer

LATE_TOLERANCE_S = 0.01  # a batch sent within this of its time is on time (sleep granularity)


@dataclass(frozen=True)
class ReplayResult:
    """What `replay` did: samples and batches sent (calls of `send`), batches sent later than LATE_TOLERANCE_S after
    their time, the largest such delay, and the wall time taken on the clock."""

    samples: int
    batches: int
    late_batches: int
    max_delay_s: float
    wall_s: float


def replay(
    samples: Sequence[dict], send: Callable[[list[dict]], None], *, speed: float = 1.0, batch: int = 1, clock=time
) -> ReplayResult:
    """Send `samples` (wire-format dicts with vehicle_id and timestamp_ms) to `send` in time order at `speed` times
    real time (0 or math.inf: as fast as possible), `batch` samples of one vehicle per call; see the module docstring.
    `clock` provides `monotonic()` and `sleep(seconds)` (the `time` module, or a fake one in tests). An exception of
    `send` ends the replay and propagates."""
    if isinstance(speed, bool) or not isinstance(speed, (int, float)) or math.isnan(speed) or speed < 0:
        raise ValueError(f"speed must be a number >= 0 (0 or inf: as fast as possible), got {speed!r}")
    if isinstance(batch, bool) or not isinstance(batch, int) or batch < 1:
        raise ValueError(f"batch must be a whole number >= 1, got {batch!r}")
    for i, s in enumerate(samples):
        if not isinstance(s, dict):
            raise TypeError(f"sample {i} must be a dict, got {type(s).__name__}")
        ts = s.get("timestamp_ms")
        if isinstance(ts, bool) or not isinstance(ts, int):
            raise TypeError(f"sample {i} needs an integer timestamp_ms, got {ts!r}")
    order = sorted(range(len(samples)), key=lambda i: samples[i]["timestamp_ms"])
    paced = 0 < speed < math.inf
    start = clock.monotonic()
    if not order:
        return ReplayResult(0, 0, 0, 0.0, 0.0)
    t0 = samples[order[0]]["timestamp_ms"]
    last_of = {}  # vehicle -> its last position in `order`, to flush its final, partial batch
    for pos, i in enumerate(order):
        last_of[samples[i].get("vehicle_id")] = pos
    pending: dict[object, list[dict]] = {}
    batches = late = 0
    max_delay = 0.0
    for pos, i in enumerate(order):
        sample = samples[i]
        vehicle = sample.get("vehicle_id")
        queue = pending.setdefault(vehicle, [])
        queue.append(sample)
        if len(queue) < batch and last_of[vehicle] != pos:
            continue
        if paced:
            due = start + (sample["timestamp_ms"] - t0) / 1000.0 / speed
            wait = due - clock.monotonic()
            if wait > 0:
                clock.sleep(wait)
            delay = clock.monotonic() - due
            if delay > LATE_TOLERANCE_S:
                late += 1
                max_delay = max(max_delay, delay)
        send(queue)
        pending[vehicle] = []
        batches += 1
    return ReplayResult(len(order), batches, late, max_delay, clock.monotonic() - start)


def replay_file(
    path: str | Path,
    importer: str | Importer | None = None,
    *,
    vehicle_id: str | None = None,
    start_ms: int | None = None,
    **options,
) -> list[dict]:
    """The samples of the log at `path` as wire-format v1 dicts in time order, imported by `importer` (a name, an
    importer, or None: the one that recognises the file). `vehicle_id` and `start_ms` as the importer documents
    (None: its default); other options go to the importer. Optional fields the log lacks are left out of the dicts
    rather than sent as null."""
    path = Path(path)
    chosen = resolve_importer(path, importer)
    if vehicle_id is not None:
        options["vehicle_id"] = vehicle_id
    if start_ms is not None:
        options["start_ms"] = start_ms
    table = chosen.load(path, **options)
    order = sorted(range(table.num_rows), key=table["timestamp_ms"].to_pylist().__getitem__)
    rows = table.to_pylist()
    return [{k: v for k, v in rows[i].items() if v is not None} for i in order]
