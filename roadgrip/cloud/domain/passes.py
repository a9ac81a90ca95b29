"""The pass rule (CONTRACTS 3.6), owned here for the friction map (friction_map.py) and the warning engine (warnings.py):
both take a vehicle's estimates as passes, and they must cut them the same way.

A pass is one vehicle's consecutive estimates in one cell. One vehicle's estimates in one pass share its estimator's
state, tires and bias: the map counts them as one piece of evidence, the engine judges them together.

1. Order. A call's rows with a position are taken in (vehicle, timestamp) order (`in_pass_order`); rows without one
   belong to no cell and are left out.
2. A pass ends when the vehicle is seen in another cell, when it comes back to the cell more than pass_gap_s after the
   pass's last estimate, or when the clock (a call's now_ms) is more than pass_gap_s past that estimate
   (`close_idle`). A pass's time is its last estimate's timestamp.
3. Late rows. A row of the vehicle's open pass's cell, within pass_gap_s of its last estimate, joins it, even when
   older than that estimate, unless it is no newer than the end of the vehicle's last closed pass. Any other row older
   than the last estimate of the vehicle's open pass, and any row no newer than the end of its last closed pass,
   arrives too late to go into a pass: the pass it belonged to is closed (the engine has judged it, the map has
   counted it). It is dropped and counted (`late_rows`).
4. Otherwise the row starts a new pass, closing the vehicle's open one.

Each consumer forgets a vehicle's last closed pass once evidence that old no longer counts for it (`forget`: the
engine after validity_s, the map after max_age_s); a row older than that, arriving after, starts a pass again.

Visits, which the engine counts instead of passes: one vehicle's passes closer than pass_gap_s to the one before (from
its end to the next one's start) are one visit (`new_visit`). GNSS noise along a cell border splits one drive past
into several passes in a few seconds: one observation, not repeated ones.

`Passes` applies the rule to the consumer's own pass objects (subclasses of `Pass`, which add what the consumer keeps
of a pass): `row` says which pass a row goes into, and every pass that ends is handed to the consumer's `on_close`.
"""

from __future__ import annotations

import operator
from collections.abc import Callable, Iterable

_NEVER = -(2**62)
_PASS_ORDER = operator.itemgetter("vehicle_id", "timestamp_ms")


class Pass:
    """The bounds of one vehicle's pass in one cell; consumers subclass it with what they keep of the pass."""

    __slots__ = ("cell", "first_ms", "last_ms", "vehicle_id")

    def __init__(self, vehicle_id: str, cell: str, t: int):
        self.vehicle_id, self.cell, self.first_ms, self.last_ms = vehicle_id, cell, t, t


def in_pass_order(rows: Iterable[dict]) -> list[dict]:
    """The rows with a position, in (vehicle, timestamp) order (rule 1)."""
    kept = [r for r in rows if r["latitude_deg"] is not None and r["longitude_deg"] is not None]
    kept.sort(key=_PASS_ORDER)
    return kept


def new_visit(end_before_ms: float | None, start_ms: float, gap_ms: float) -> bool:
    """Whether a vehicle's pass starting at start_ms begins a new visit (module docstring) after the vehicle's pass
    before it, which ended at end_before_ms (None: it has none)."""
    return end_before_ms is None or start_ms - end_before_ms > gap_ms


class Passes:
    """The pass rule (module docstring) over every vehicle: its pass in progress (`open`, vehicle_id -> pass) and the end
    of its last closed pass (`closed_ms`). `new_pass(vehicle_id, cell, t)` makes the consumer's pass object;
    `on_close(pass)` takes each pass that ends."""

    __slots__ = ("closed_ms", "gap_ms", "late_rows", "new_pass", "on_close", "open")

    def __init__(self, pass_gap_s: float, new_pass: Callable[[str, str, int], Pass], on_close: Callable[[Pass], None]):
        self.gap_ms = pass_gap_s * 1000.0
        self.new_pass = new_pass
        self.on_close = on_close
        self.open: dict[str, Pass] = {}
        self.closed_ms: dict[str, int] = {}
        self.late_rows = 0

    def row(self, vehicle_id: str, cell: str, t: int) -> Pass | None:
        """The pass a row of `vehicle_id` in `cell` at `t` goes into (rules 2-4; a new one opened, the vehicle's previous
        one closed, when it starts one), or None for a late row (counted). Rows of one vehicle in time order."""
        current = self.open.get(vehicle_id)
        if current is not None and current.cell == cell and t - current.last_ms <= self.gap_ms:
            if t < current.first_ms:
                if t <= self.closed_ms.get(vehicle_id, _NEVER):
                    self.late_rows += 1
                    return None
                current.first_ms = t
            elif t > current.last_ms:
                current.last_ms = t
            return current
        if (current is not None and t < current.last_ms) or t <= self.closed_ms.get(vehicle_id, _NEVER):
            self.late_rows += 1
            return None
        if current is not None:
            del self.open[vehicle_id]
            self._ended(current)
        p = self.open[vehicle_id] = self.new_pass(vehicle_id, cell, t)
        return p

    def close_idle(self, now_ms: int) -> None:
        """Close the passes whose last estimate is more than pass_gap_s before now_ms (rule 2)."""
        gap_ms = self.gap_ms
        for p in [p for p in self.open.values() if now_ms - p.last_ms > gap_ms]:
            del self.open[p.vehicle_id]
            self._ended(p)

    def resume(self, p: Pass) -> None:
        """Take back a pass in progress saved elsewhere (a map's cell state): it stays open unless the vehicle has a
        newer one open, which it then precedes (closed at once); an older open one is closed."""
        current = self.open.get(p.vehicle_id)
        if current is not None and current.last_ms >= p.last_ms:
            self._ended(p)
            return
        if current is not None:
            self._ended(current)
        self.open[p.vehicle_id] = p

    def forget(self, horizon_ms: float) -> None:
        """Forget the last closed pass of each vehicle without an open one whose last closed pass ended before
        horizon_ms."""
        for vehicle in [v for v, t in self.closed_ms.items() if t < horizon_ms and v not in self.open]:
            del self.closed_ms[vehicle]

    def clear(self) -> None:
        self.open.clear()
        self.closed_ms.clear()
        self.late_rows = 0

    def _ended(self, p: Pass) -> None:
        if p.last_ms > self.closed_ms.get(p.vehicle_id, _NEVER):
            self.closed_ms[p.vehicle_id] = p.last_ms
        self.on_close(p)
