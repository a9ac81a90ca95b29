"""Where the vehicle end's samples come from (wire format v1 dicts of one vehicle, in time order):

- `WireLines`: lines of wire format (NDJSON: one JSON object per line, wire or VSS keys, CONTRACTS 3.1) from stdin
  or a file, each checked by the cloud's own wire parser (roadgrip/cloud/ingest/wire.py); a refused line is skipped
  with a one-line warning naming the line, the field and why, and counted (`WireLines.rejected`).
- `log_samples`: a recorded log through the importers of `roadgrip import-log` (roadgrip/fleet/importers/: wire files,
  the BMW M8 log, raw CAN logs with a DBC and a mapping file).
- `CanSampler`: a live CAN interface through python-can (any of its interfaces: socketcan on the car, `virtual` in
  tests), decoded with the car's DBC through cantools and the same mapping file as `import-log`'s can-dbc importer
  (roadgrip/fleet/importers/can_mapping.py, checked against the DBC the same way), sampled on the 100 ms grid as that
  importer resamples a log: at each instant every field's latest value at or before it (zero-order hold), kept only
  when every mapped signal's latest frame is at most its max_age_s old. One interface carries every signal: the
  mapping's bus numbers are not used (on a car with several buses, a gateway or a bridge joins them); frames are
  matched by frame id. An instant is emitted once a frame later than it has arrived (a live terminal cannot know a
  signal's value at an instant sooner).
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Iterable, Iterator
from pathlib import Path

import can
import cantools
import numpy as np

from roadgrip.cloud.ingest.wire import PayloadError, parse_payload
from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.fleet.importers import resolve_importer
from roadgrip.fleet.importers.can_dbc import PERIOD_MS, load_dbc, to_field
from roadgrip.fleet.importers.can_mapping import check_against_dbc, load_mapping

log = logging.getLogger(__name__)


class WireLines:
    """The samples of NDJSON lines (module docstring); `rejected` counts the refused lines."""

    def __init__(self, lines: Iterable[bytes | str], vehicle_id: str | None = None, max_future_s: float = 60.0):
        self.lines = lines
        self.vehicle_id = vehicle_id
        self.max_future_ms = int(max_future_s * 1000)
        self.rejected = 0

    def __iter__(self) -> Iterator[dict]:
        for number, line in enumerate(self.lines, start=1):
            body = line.encode() if isinstance(line, str) else line
            if not body.strip():
                continue
            try:
                samples, errors = parse_payload(
                    body,
                    content_type="application/x-ndjson",
                    now_ms=int(time.time() * 1000),
                    max_future_ms=self.max_future_ms,
                    vehicle_id=self.vehicle_id,
                )
            except PayloadError as exc:
                samples, errors = [], [exc]
            for error in errors:
                self.rejected += 1
                where = f"field {error.field}: " if getattr(error, "field", None) else ""
                log.warning("line %d refused: %s%s", number, where, getattr(error, "reason", error))
            yield from samples


def log_samples(path: str | Path, importer: str | None = None, **options) -> Iterator[dict]:
    """The samples of a recorded log, through `roadgrip import-log`'s importers."""
    table = resolve_importer(path, importer).load(Path(path), **options)
    yield from table.select(list(TELEMETRY_COLUMNS)).to_pylist()


class CanSampler:
    """Wire-format samples from a live CAN bus (module docstring). Iterate it; it ends when `stop()` is called or
    no frame came for `idle_timeout_s`."""

    def __init__(
        self,
        bus: can.BusABC,
        dbc_path: str | Path,
        mapping_path: str | Path,
        vehicle_id: str | None = None,
        idle_timeout_s: float = 5.0,
    ):
        self.bus = bus
        self.mapping = load_mapping(mapping_path)
        db = load_dbc(dbc_path)
        messages = check_against_dbc(self.mapping, db, Path(dbc_path).name)
        self.vehicle_id = vehicle_id or self.mapping.vehicle_id
        if self.vehicle_id is None:
            raise ValueError(f"no vehicle_id: the mapping {Path(mapping_path).name} names none; pass one")
        self.by_frame: dict[int, tuple[object, list]] = {}
        for source, message in messages.items():
            self.by_frame.setdefault(message.frame_id, (message, []))[1].append(source)
        self.sources = list(messages)
        self.idle_timeout_s = idle_timeout_s
        self.latest: dict = {}  # source -> (time ms, value in the DBC's unit)
        self.undecodable = 0
        self._next_ms: int | None = None
        self._stopped = False

    def stop(self) -> None:
        self._stopped = True

    def __iter__(self) -> Iterator[dict]:
        while not self._stopped:
            frame = self.bus.recv(timeout=self.idle_timeout_s)
            if frame is None:
                return
            yield from self.frame(frame)

    def frame(self, frame: can.Message) -> list[dict]:
        """Take one frame; the samples of the grid instants it completes."""
        entry = self.by_frame.get(frame.arbitration_id)
        t_ms = frame.timestamp * 1000.0
        out = []
        if self._next_ms is None:
            self._next_ms = math.ceil(t_ms / PERIOD_MS) * PERIOD_MS
        while self._next_ms < t_ms:
            sample = self._sample(self._next_ms)
            if sample is not None:
                out.append(sample)
            self._next_ms += PERIOD_MS
        if entry is not None:
            message, sources = entry
            try:
                decoded = message.decode(bytes(frame.data), decode_choices=False)
            except (ValueError, cantools.database.errors.Error) as exc:
                self.undecodable += 1
                if self.undecodable == 1:
                    log.warning("CAN frame %s (id %d) did not decode: %s", message.name, frame.arbitration_id, exc)
                return out
            for source in sources:
                self.latest[source] = (t_ms, sum(float(decoded[name]) for name in source.signals))
        return out

    def _sample(self, grid_ms: int) -> dict | None:
        sample = dict.fromkeys(TELEMETRY_COLUMNS)
        sample["vehicle_id"], sample["timestamp_ms"] = self.vehicle_id, grid_ms
        radius = self.mapping.profile.wheel_radius_m
        for source in self.sources:
            held = self.latest.get(source)
            if held is None or grid_ms - held[0] > source.max_age_s * 1000.0 + 1e-6:
                return None
            value = to_field(source, np.array([held[1]]), radius)[0]
            sample[source.field] = bool(value) if value.dtype == bool else float(value)
        for field, value in self.mapping.constants.items():
            sample[field] = value
        return sample


def read_lines(path: str | Path | None) -> Iterable[bytes]:
    """The lines of a file, or of stdin for None or '-'."""
    if path is None or str(path) == "-":
        return sys.stdin.buffer
    return Path(path).open("rb")
