"""Slippery-road warnings per H3 cell (DESIGN 3.6), in the shape of an ETSI DENM (cause code 6,
adverseWeatherCondition-Adhesion).

Pure and in memory: `update(estimates, now_ms)` takes estimate rows (DESIGN 3.4 dicts with vehicle_id, timestamp_ms,
latitude_deg, longitude_deg, mu, mu_lower, mu_upper, excited) and returns the WarningEvents it caused. Rows without a
position are ignored.

Rules
1. Passes. A pass is one vehicle's consecutive estimates in one cell. It ends when the vehicle is seen in another cell,
   when it comes back to the cell after more than pass_gap_s, or when now_ms is more than pass_gap_s past its last
   estimate. A pass's time is its last estimate's timestamp. Rows are taken in (vehicle, timestamp) order within a call;
   a row older than its vehicle's current pass from another cell, or older than the vehicle's last judged pass, arrives
   too late to change a verdict and is dropped (counted in `late_rows_`). A late row of the current pass's cell joins
   the pass.
2. Verdict of a pass, from its excited estimates only (a non-excited estimate says nothing about mu):
   "low" with at least min_excited_per_pass of them and their median mu_upper < threshold_mu (even the optimistic
   bound is slippery); "dry" with at least min_excited_per_pass and their median mu_lower >= threshold_mu (even the
   pessimistic bound has grip); otherwise "unknown", which changes nothing. Medians, so that a few outliers in a pass of
   tens of samples cannot decide it. The two are exclusive since mu_lower <= mu_upper sample by sample.
3. Passes are applied to their cells in order of their time, all those ended in one call together, and every rule
   compares pass times, not arrival order, so that how the estimates are batched matters little.
4. Raise: a cell gets a warning when it holds at least min_low_passes low passes (of two vehicles, or repeated passes
   of one) later than its last dry pass and at most validity_s old. One vehicle's passes less than pass_gap_s apart
   count once (`_independent`): GNSS noise along a cell border splits one visit into several passes. Only low
   passes in the cell itself count: a warning never appears in a cell without them.
5. Refresh: a low pass in a cell with an active warning extends it (an "active" event with a higher sequence_number).
6. Cancel ("recovered"): min_dry_passes dry passes later than the detection cancel it. A dry pass also clears the
   cell's earlier low passes (rule 4 counts only low passes after the last dry one).
7. Expire ("expired"): a warning lapses validity_s after its last low pass (evidence_ms + validity_s, the DENM's own
   validity counted from its detectionTime). The check runs at every update against now_ms, and before a pass is
   applied to its cell against the pass's time.

Events: every raise, refresh, cancellation and expiry is a WarningEvent (frozen). warning_id = f"{cell}-{detection_ms}"
is stable for a warning's life; sequence_number counts its events (0 when raised); action_sequence_number is the
DENM ActionID sequenceNumber (0..65535), one per warning, kept through its updates and its cancellation.
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

import h3

from roadgrip.cloud.exports import MAX_VALIDITY_S, denm
from roadgrip.cloud.friction_map import validate_resolution

LOW, DRY, UNKNOWN = "low", "dry", "unknown"
ACTIVE, CANCELLED = "active", "cancelled"
LOW_FRICTION, RECOVERED, EXPIRED = "low friction", "recovered", "expired"
_NEVER = -(2**62)


@dataclass(frozen=True)
class WarningEvent:
    """A raise, refresh, cancellation or expiry of a slippery-road warning in one H3 cell. Times in ms since the Unix
    epoch (UTC)."""

    warning_id: str  # f"{cell}-{detection_ms}", stable for the warning's life
    cell: str
    status: str  # "active" | "cancelled"
    reason: str  # "low friction" | "recovered" | "expired"
    detection_ms: int  # when the warning was raised (the time of the low pass that completed the evidence)
    updated_ms: int  # when this event was generated (the update's now_ms; DENM referenceTime)
    latitude_deg: float  # cell centre
    longitude_deg: float
    mu_upper: float  # the evidence: median over the low passes of each pass's median mu_upper
    n_passes: int  # low passes in the evidence
    n_vehicles: int  # distinct vehicles among them
    sequence_number: int  # 0 when raised, +1 for each later event of the same warning
    validity_s: float  # counted from evidence_ms
    evidence_ms: int  # the time of what this event reports (DENM detectionTime): the low pass that raised or
    # refreshed it, the dry pass that cancelled it, or the instant it lapsed
    action_sequence_number: int  # DENM ActionID sequenceNumber, one per warning
    station_id: int = 1  # DENM originating station

    def to_denm(self) -> dict:
        """This event as a DENM (roadgrip.cloud.exports.denm)."""
        return denm(self)


class _LowPass(NamedTuple):
    time_ms: int
    vehicle_id: str
    mu_upper: float  # median mu_upper of the pass's excited estimates


class _Pass:
    __slots__ = ("cell", "first_ms", "last_ms", "lowers", "uppers", "vehicle_id")

    def __init__(self, vehicle_id: str, cell: str, t: int):
        self.vehicle_id, self.cell, self.first_ms, self.last_ms = vehicle_id, cell, t, t
        self.uppers: list[float] = []
        self.lowers: list[float] = []


class _Warning:
    __slots__ = (
        "action_sequence_number",
        "detection_ms",
        "dry_passes",
        "evidence_ms",
        "last_event",
        "sequence_number",
        "warning_id",
    )

    def __init__(self, warning_id: str, detection_ms: int, action_sequence_number: int, sequence_number: int = 0):
        self.warning_id, self.detection_ms, self.evidence_ms = warning_id, detection_ms, detection_ms
        self.action_sequence_number, self.sequence_number = action_sequence_number, sequence_number
        self.dry_passes = 0
        self.last_event: WarningEvent | None = None


class _CellState:
    __slots__ = ("last_dry_ms", "low_passes", "warning")

    def __init__(self):
        self.low_passes: list[_LowPass] = []
        self.last_dry_ms = _NEVER
        self.warning: _Warning | None = None


def _count(name: str, value) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return value


def _positive(name: str, value, upper: float = math.inf) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0 < value <= upper:
        raise ValueError(f"{name} must be a number in (0, {upper}], got {value!r}")
    return float(value)


class WarningEngine:
    """Slippery-road warnings from low-friction passes; see the module docstring for the rules."""

    def __init__(self, resolution: int = 10, threshold_mu: float = 0.4, min_low_passes: int = 2,
                 min_dry_passes: int = 1, pass_gap_s: float = 30.0, min_excited_per_pass: int = 3,
                 validity_s: float = 600.0, station_id: int = 1):
        self.resolution = validate_resolution(resolution)
        self.threshold_mu = _positive("threshold_mu", threshold_mu)
        self.min_low_passes = _count("min_low_passes", min_low_passes)
        self.min_dry_passes = _count("min_dry_passes", min_dry_passes)
        self.pass_gap_s = _positive("pass_gap_s", pass_gap_s)
        self.min_excited_per_pass = _count("min_excited_per_pass", min_excited_per_pass)
        self.validity_s = _positive("validity_s", validity_s, MAX_VALIDITY_S)  # a DENM cannot say more
        if isinstance(station_id, bool) or not isinstance(station_id, int) or not 0 <= station_id <= 4294967295:
            raise ValueError(f"station_id must be an integer StationID in 0..4294967295, got {station_id!r}")
        self.station_id = station_id
        self.open_passes_: dict[str, _Pass] = {}  # vehicle_id -> its pass in progress
        self.last_judged_ms_: dict[str, int] = {}  # vehicle_id -> time of its last judged pass
        self.cell_states_: dict[str, _CellState] = {}
        self.active_cells_: set[str] = set()
        self.next_action_sequence_number_ = 0
        self.late_rows_ = 0
        self.last_sweep_ms_ = _NEVER

    # ------------------------------------------------------------------------------------------------------ public

    def update(self, estimates: Iterable[dict], now_ms: int) -> list[WarningEvent]:
        """Feed estimate rows; the events (raised, refreshed, cancelled, expired) this update caused, in the order
        applied: passes by time, then the expiries at now_ms."""
        now_ms = int(now_ms)
        gap_ms = self.pass_gap_s * 1000.0
        rows = [r for r in estimates if r["latitude_deg"] is not None and r["longitude_deg"] is not None]
        rows.sort(key=lambda r: (r["vehicle_id"], r["timestamp_ms"]))
        closed: list[_Pass] = []
        resolution = self.resolution
        to_cell = h3.latlng_to_cell
        open_passes = self.open_passes_
        for row in rows:
            vehicle = row["vehicle_id"]
            t = int(row["timestamp_ms"])
            cell = to_cell(row["latitude_deg"], row["longitude_deg"], resolution)
            current = open_passes.get(vehicle)
            if current is not None and current.cell == cell and t - current.last_ms <= gap_ms:
                if t < current.first_ms and t <= self.last_judged_ms_.get(vehicle, _NEVER):
                    self.late_rows_ += 1
                    continue
                current.first_ms = min(current.first_ms, t)
                current.last_ms = max(current.last_ms, t)
            elif current is not None and t < current.last_ms:
                self.late_rows_ += 1  # late row of another cell: its pass there was judged already
                continue
            else:
                if t <= self.last_judged_ms_.get(vehicle, _NEVER):
                    self.late_rows_ += 1
                    continue
                if current is not None:
                    closed.append(self._close(current))
                current = open_passes[vehicle] = _Pass(vehicle, cell, t)
            if row["excited"]:
                lo, hi = row["mu_lower"], row["mu_upper"]
                if not (math.isfinite(lo) and math.isfinite(hi)):
                    raise ValueError(f"estimate of vehicle {vehicle!r} at {t}: mu_lower {lo!r} and mu_upper {hi!r} "
                                     f"must be finite")
                current.lowers.append(lo)
                current.uppers.append(hi)
        for vehicle, current in list(open_passes.items()):
            if now_ms - current.last_ms > gap_ms:  # no estimate from it for pass_gap_s: the pass is over
                closed.append(self._close(current))
        closed.sort(key=lambda p: (p.last_ms, p.cell, p.vehicle_id))
        events: list[WarningEvent] = []
        for finished in closed:
            self._apply(finished, now_ms, events)
        self._expire(now_ms, events)
        if now_ms - self.last_sweep_ms_ >= gap_ms:
            self._sweep(now_ms)
        return events

    def active(self) -> list[WarningEvent]:
        """The latest event of every active warning, ordered by cell."""
        return [self.cell_states_[c].warning.last_event for c in sorted(self.active_cells_)]

    def restore(self, events: Iterable[WarningEvent]) -> None:
        """Re-load active warnings after a restart (cancelled events are skipped; of two for one cell the later
        wins). Counts and the median are kept, not the passes behind them: the evidence is re-seeded as n_passes passes
        at evidence_ms with the event's mu_upper, from n_vehicles placeholder vehicles, so a vehicle seen before the
        restart and again after counts twice."""
        for event in events:
            if event.status != ACTIVE:
                continue
            state = self.cell_states_.setdefault(event.cell, _CellState())
            if state.warning is not None and state.warning.last_event.updated_ms >= event.updated_ms:
                continue
            warning = _Warning(event.warning_id, event.detection_ms, event.action_sequence_number,
                               event.sequence_number)
            warning.evidence_ms = event.evidence_ms
            warning.last_event = event
            state.warning = warning
            n_vehicles = max(1, event.n_vehicles)
            state.low_passes = [_LowPass(event.evidence_ms, f"restored-{k % n_vehicles}", event.mu_upper)
                                for k in range(max(1, event.n_passes))]
            self.active_cells_.add(event.cell)
            self.next_action_sequence_number_ = max(self.next_action_sequence_number_,
                                                    (event.action_sequence_number + 1) % 65536)

    # ----------------------------------------------------------------------------------------------------- passes

    def _close(self, finished: _Pass) -> _Pass:
        del self.open_passes_[finished.vehicle_id]
        judged = self.last_judged_ms_.get(finished.vehicle_id, _NEVER)
        self.last_judged_ms_[finished.vehicle_id] = max(judged, finished.last_ms)
        return finished

    def _independent(self, low_passes: list[_LowPass]) -> int:
        """Low passes that count as separate evidence: one vehicle's passes closer than pass_gap_s to each other are
        one visit (a vehicle driving along a cell border, GNSS noise moving it in and out, makes several passes in
        a few seconds; they are one observation, not repeated passes)."""
        gap_ms = self.pass_gap_s * 1000.0
        count, last_by_vehicle = 0, {}
        for p in sorted(low_passes, key=lambda p: p.time_ms):
            last = last_by_vehicle.get(p.vehicle_id)
            if last is None or p.time_ms - last > gap_ms:
                count += 1
            last_by_vehicle[p.vehicle_id] = p.time_ms
        return count

    def verdict(self, uppers: list[float], lowers: list[float]) -> str:
        """The verdict of a pass from the mu_upper and mu_lower of its excited estimates (rule 2)."""
        if len(uppers) < self.min_excited_per_pass:
            return UNKNOWN
        if statistics.median(uppers) < self.threshold_mu:
            return LOW
        if statistics.median(lowers) >= self.threshold_mu:
            return DRY
        return UNKNOWN

    def _apply(self, finished: _Pass, now_ms: int, events: list[WarningEvent]) -> None:
        verdict = self.verdict(finished.uppers, finished.lowers)
        if verdict == UNKNOWN:
            return
        t = finished.last_ms
        validity_ms = self.validity_s * 1000.0
        state = self.cell_states_.setdefault(finished.cell, _CellState())
        warning = state.warning
        if warning is not None and t >= warning.evidence_ms + validity_ms:  # it lapsed before this pass (rule 7)
            self._end(finished.cell, state, EXPIRED, int(warning.evidence_ms + validity_ms), now_ms, events)
            warning = None
        if verdict == DRY:
            state.last_dry_ms = max(state.last_dry_ms, t)
            state.low_passes = [p for p in state.low_passes if p.time_ms > t]
            if warning is not None and t > warning.detection_ms:
                warning.dry_passes += 1
                if warning.dry_passes >= self.min_dry_passes:
                    self._end(finished.cell, state, RECOVERED, t, now_ms, events)
            return
        if t <= state.last_dry_ms:
            return  # superseded by a later dry pass (rule 4)
        horizon = max(now_ms, t) - validity_ms
        state.low_passes = [p for p in state.low_passes if p.time_ms >= horizon]
        state.low_passes.append(_LowPass(t, finished.vehicle_id, statistics.median(finished.uppers)))
        if warning is None:
            if self._independent(state.low_passes) >= self.min_low_passes:
                warning = state.warning = _Warning(f"{finished.cell}-{t}", t, self.next_action_sequence_number_)
                self.next_action_sequence_number_ = (self.next_action_sequence_number_ + 1) % 65536
                self.active_cells_.add(finished.cell)
                events.append(self._event(finished.cell, state, ACTIVE, LOW_FRICTION, now_ms))
        else:
            warning.evidence_ms = max(warning.evidence_ms, t)
            warning.sequence_number += 1
            events.append(self._event(finished.cell, state, ACTIVE, LOW_FRICTION, now_ms))

    # --------------------------------------------------------------------------------------------------- warnings

    def _event(self, cell: str, state: _CellState, status: str, reason: str, now_ms: int) -> WarningEvent:
        warning = state.warning
        if status == ACTIVE:
            evidence = state.low_passes
            mu_upper = statistics.median(p.mu_upper for p in evidence)
            n_passes, n_vehicles = self._independent(evidence), len({p.vehicle_id for p in evidence})
        else:  # a cancellation reports the low-friction evidence the warning had
            previous = warning.last_event
            mu_upper, n_passes, n_vehicles = previous.mu_upper, previous.n_passes, previous.n_vehicles
        latitude_deg, longitude_deg = h3.cell_to_latlng(cell)
        event = WarningEvent(
            warning_id=warning.warning_id, cell=cell, status=status, reason=reason,
            detection_ms=warning.detection_ms, updated_ms=max(now_ms, warning.evidence_ms),
            latitude_deg=latitude_deg, longitude_deg=longitude_deg, mu_upper=mu_upper, n_passes=n_passes,
            n_vehicles=n_vehicles, sequence_number=warning.sequence_number, validity_s=self.validity_s,
            evidence_ms=warning.evidence_ms, action_sequence_number=warning.action_sequence_number,
            station_id=self.station_id)
        warning.last_event = event
        return event

    def _end(self, cell: str, state: _CellState, reason: str, evidence_ms: int, now_ms: int,
             events: list[WarningEvent]) -> None:
        warning = state.warning
        warning.sequence_number += 1
        warning.evidence_ms = max(warning.evidence_ms, evidence_ms)
        events.append(self._event(cell, state, CANCELLED, reason, now_ms))
        state.warning = None
        self.active_cells_.discard(cell)
        if reason == EXPIRED:
            state.low_passes = []  # its evidence is older than validity_s

    def _expire(self, now_ms: int, events: list[WarningEvent]) -> None:
        validity_ms = self.validity_s * 1000.0
        for cell in sorted(self.active_cells_):
            state = self.cell_states_[cell]
            lapse_ms = state.warning.evidence_ms + validity_ms
            if now_ms >= lapse_ms:
                self._end(cell, state, EXPIRED, int(lapse_ms), now_ms, events)

    def _sweep(self, now_ms: int) -> None:
        """Forget cells with no warning whose evidence (low passes, last dry pass) is older than validity_s, and the
        last judged pass of vehicles gone for as long."""
        horizon = now_ms - self.validity_s * 1000.0
        for cell in [c for c, s in self.cell_states_.items() if s.warning is None]:
            state = self.cell_states_[cell]
            state.low_passes = [p for p in state.low_passes if p.time_ms >= horizon]
            if not state.low_passes and state.last_dry_ms < horizon:
                del self.cell_states_[cell]
        for vehicle in [v for v, t in self.last_judged_ms_.items() if t < horizon and v not in self.open_passes_]:
            del self.last_judged_ms_[vehicle]
        self.last_sweep_ms_ = now_ms
