"""Slippery-road warnings per H3 cell (CONTRACTS 3.6), in the shape of an ETSI DENM (cause code 6,
adverseWeatherCondition-Adhesion).

This module owns the warning rules 2-9 below, the product's warning settings (THRESHOLD_MU, ...; Settings takes them
as defaults) and the longest validity a DENM can carry (MAX_VALIDITY_S). Rule 1, what a pass is, is passes.py's,
the friction map's too, and so is what a visit is (rules 4, 6, 9); the cell of a position is cells.py's; the argument
checks are checks.py's. Writing an event as a DENM is roadgrip/cloud/formats/denm.py's; where in a cell a warning's
low evidence lies, and which dry pass speaks of it (rule 9), is roadgrip/cloud/domain/places.py's.

Pure and in memory: `update(estimates, now_ms)` takes estimate rows (CONTRACTS 3.4 dicts with vehicle_id, timestamp_ms,
latitude_deg, longitude_deg, mu, mu_lower, mu_upper, excited) and returns the WarningEvents it caused. Rows without a
position are ignored. `station_evidence(rows, now_ms)` takes the evidence of roadside stations' reports
(roadgrip/cloud/domain/stations.py: dicts with station_id, cell, timestamp_ms, mu, mu_lower, mu_upper) the same way (rule 8).

Rules
1. Passes. A pass is one vehicle's consecutive estimates in one cell. It ends when the vehicle is seen in another cell,
   when it comes back to the cell after more than pass_gap_s, or when now_ms is more than pass_gap_s past its last
   estimate. A pass's time is its last estimate's timestamp. The rule, late rows included, is
   roadgrip/cloud/domain/passes.py's, the friction map's too: rows are taken in (vehicle, timestamp) order within a
   call; a row older than its vehicle's current pass from another cell, or no newer than the vehicle's last judged
   pass, arrives too late to change a verdict and is dropped (counted in `late_rows_`); a late row of the current
   pass's cell joins the pass. A vehicle's last judged pass is forgotten after validity_s.
2. Verdict of a pass, from its excited estimates (a non-excited estimate's interval says nothing about mu) and from
   what its estimates prove: "low" with at least min_excited_per_pass excited ones and their median mu_upper <
   threshold_mu (even the optimistic bound is slippery); otherwise "dry" when the largest mu_proven of its estimates,
   excited or not, reaches threshold_mu (the car's own acceleration showed that much grip there: a calm pass cornering
   at 0.45 g is a dry pass), or with at least min_excited_per_pass excited ones whose median mu_lower >= threshold_mu
   (even the pessimistic bound has grip); otherwise "unknown", which changes nothing. Medians, so that a few outliers
   in a pass of tens of samples cannot decide it. "Low" is judged first: a pass whose estimates read low although one
   of its samples proved grip straddles a patch's edge within the cell, and the low reading is the one that warns.
   A low pass's time is the time of its last low reading (`_Pass.evidence_ms`): the ice was under the car then; its
   later estimates in the cell, on the way out, are not evidence of ice. Every rule below that speaks of a low pass's
   time (raising, refreshing, superseding, the validity) means that one; any other pass's time is rule 1's.
3. Passes are applied to their cells in order of their time, all those ended in one call together, and every rule
   compares pass times, not arrival order, so that how the estimates are batched matters little.
4. Raise: a cell gets a warning when it holds at least min_low_passes low passes (1 by default: a vehicle whose
   excited estimates say mu_upper < threshold_mu is evidence enough; with 2, two vehicles or repeated passes of one)
   later than the last dry pass over the cell's place (rule 9) and at most validity_s old. One vehicle's passes less
   than pass_gap_s apart are one visit and count once (`_Evidence`; what a visit is, passes.py's): GNSS noise along a
   cell border splits one visit into several passes. Only low passes in the cell itself count: a warning never appears
   in a cell without them.
5. Refresh: a low pass in a cell with an active warning extends it (an "active" event with a higher sequence_number).
6. Cancel ("recovered"): it ends when its place is shown dry (rule 9: grip proven on every spot of it after the spot's
   last low reading, and the ice it continues into next door shown dry too) and at least min_dry_passes dry passes later
   than the detection spoke of the place (one vehicle's dry passes closer than pass_gap_s to the one before are one
   visit, counted once, as its low passes are in rule 4: a visit across a cell border may speak of the place from both
   cells). A dry pass elsewhere in the cell neither cancels nor refreshes it. The pass that shows the place dry also
   clears the cell's earlier low passes (rule 4 counts only low passes after the last such dry pass), and the places
   next door that waited on it (`_settle`).
7. Expire ("expired"): a warning lapses validity_s after its last low pass's last low reading (rule 2; evidence_ms +
   validity_s, the DENM's own validity counted from its detectionTime). The check runs at every update against now_ms,
   and before a pass is applied to its cell against the pass's time.

8. Roadside stations. A station's report is one pass in each cell it covers, its own source: vehicle_id
   f"station:{station_id}" (a colon, which no vehicle_id holds), time the report's timestamp. Its verdict comes from
   the report's one interval: low when mu_upper < threshold_mu, dry when mu_lower >= threshold_mu, otherwise unknown
   (min_excited_per_pass does not apply: a report is a measurement, not a sample of a manoeuvre). It then counts by
   rules 3-7 like a vehicle's pass: a station's low reports more than pass_gap_s apart are repeated passes of one
   source (two raise a warning alone with min_low_passes 2), a dry report cancels. A report no newer than the
   station's last one applied in that cell is dropped (counted in `late_rows_`): its newest report supersedes.
   A station stands for a stretch of road (stations.py): its low report's place is the whole cell, which only a
   station's dry report speaks of; its dry report says nothing of where vehicles read low (rule 9).
9. Places (places.py). A low pass marks the spots (H3 resolution-12 cells, about 19 m across) of its estimates that
   read low (excited, mu_upper < threshold_mu); the cell's place is its spots since it was last shown dry. A dry pass
   speaks of the place when one of its estimates that proved grip (excited with mu_lower >= threshold_mu, or
   mu_proven >= threshold_mu) lies on a spot or a neighbour of one (within about 15-30 m), and shows dry the spots it
   so reaches, except those where the same pass read low (a pass across a patch's edge read ice on it and grip past
   it); a dry pass that touches no spot changes nothing in the cell. A vehicle's grip shows dry the spots it reaches in
   the places of the cells next door too: grip is proven where the tires were, whichever cell the pass is counted in
   (a spot straddles a cell border, and GNSS noise puts one pass's readings on either side of it; were a spot next door
   shown dry only by a pass in its own cell, the ice's last readings across a border would hold, as ice next door
   below, a whole patch's warnings that grip was proven over). The place is shown dry when every spot is and the
   ice it continues into in the neighbouring cells is too (`places.ice_continues`: their spots read low within
   validity_s, chained within reach of the place): grip on the rim of a patch whose ice goes on next door is not the
   patch drying. A neighbour's evidence never raises or refreshes a warning here, and a place held by it ends by
   expiry at the latest (rule 7).
   A vehicle's dry pass that begins within pass_gap_s of its own low pass in the cell is the rest of that visit (GNSS
   noise along a cell border splits a visit; rule 2 judges a visit that read low as low: grip proven just past a
   patch's edge on the way out is not the patch drying). The event carries the place not yet shown dry (`spots`, as
   of its last event), which restore() takes back; an event stored without it restores a place any dry pass in the
   cell speaks of.

Events: every raise, refresh, cancellation and expiry is a WarningEvent (frozen). warning_id = f"{cell}-{detection_ms}"
is stable for a warning's life; sequence_number counts its events (0 when raised); action_sequence_number is the
DENM ActionID sequenceNumber (0..65535), one per warning, kept through its updates and its cancellation: counted by
the engine, or taken from `action_sequence` where several engines speak for one originating station (cluster mode's
regions, roadgrip/cloud/cluster/regions.py).
"""

from __future__ import annotations

import bisect
import dataclasses
import math
import operator
import statistics
from collections.abc import Iterable
from dataclasses import dataclass
from typing import NamedTuple

import h3

from roadgrip.cloud.domain import checks
from roadgrip.cloud.domain.cells import cell_of, validate_resolution
from roadgrip.cloud.domain.passes import Pass, Passes, in_pass_order, new_visit
from roadgrip.cloud.domain.places import UNKNOWN_PLACE, Place, ice_continues, reach, spots_of

# The product's settings, in this one place (Settings.warning_* take them as defaults), as the fleet benchmark's
# trade-off curve chose them (docs/RESULTS.md, "The warning engine's thresholds"; roadgrip/evaluation/fleet_sweep.py):
# one low pass raises, at the price of warnings in the cell beside a patch where braking begun on it ends. That choice
# was made on seeds 0-2 with stations at the patches; on the tuning seeds 100-102 (issue 23) the rule picks threshold
# 0.5 and 300 s instead, not adopted here (docs/RESULTS.md).
THRESHOLD_MU = 0.4
MIN_LOW_PASSES = 1
MIN_DRY_PASSES = 1
PASS_GAP_S = 30.0
MIN_EXCITED_PER_PASS = 3
VALIDITY_S = 600.0
# The longest validity_s: a warning is published as a DENM (roadgrip/cloud/formats/denm.py), whose ValidityDuration
# (EN 302 637-3) holds 0..86400 s; a warning valid for longer could not be said to a receiver as the engine holds it.
MAX_VALIDITY_S = 86_400

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
    spots: tuple[str, ...] = ()  # the warning's place not yet shown dry (places.py: resolution-12 cells of its low
    # readings, a station's whole cell as the cell itself); what restore() takes back. Not part of the DENM


class _LowPass(NamedTuple):
    time_ms: int
    vehicle_id: str
    mu_upper: float  # median mu_upper of the pass's excited estimates


class _Evidence:
    """A cell's low passes (rule 4), oldest first, with what an event reports kept up to date as passes come and go: the
    median of their mu_upper, how many of them count as independent, how many vehicles made them. A busy cell holds
    thousands of passes within validity_s (a fleet queueing on an icy bridge), and every low pass there makes an event:
    adding or dropping a pass costs a binary search and a list insert or delete, so an event costs about the same for 3
    passes as for 3,000 (recounting them all per event made the service slower the longer it ran).

    Independent passes (`independent`): one vehicle's passes closer than pass_gap_s to the one before are one visit
    (passes.py's `new_visit`; a low pass at its time, rule 2). Of each vehicle's passes in time order, the first
    counts, and each later one that begins a new visit after its predecessor."""

    __slots__ = ("_by_vehicle", "_gap_ms", "_passes", "_uppers", "independent")

    def __init__(self, gap_ms: float):
        self._gap_ms = gap_ms
        self._passes: list[_LowPass] = []  # in time order
        self._uppers: list[float] = []  # their mu_upper, sorted
        self._by_vehicle: dict[str, list[int]] = {}  # vehicle_id -> the times of its passes, sorted
        self.independent = 0

    def __len__(self) -> int:
        return len(self._passes)

    @property
    def n_vehicles(self) -> int:
        return len(self._by_vehicle)

    def median_mu_upper(self) -> float:
        u, n = self._uppers, len(self._uppers)
        return u[n // 2] if n % 2 else (u[n // 2 - 1] + u[n // 2]) / 2  # as statistics.median

    def last_of(self, vehicle_id: str) -> int | None:
        """The time of the vehicle's latest low pass held, or None."""
        times = self._by_vehicle.get(vehicle_id)
        return times[-1] if times else None

    def add(self, p: _LowPass) -> None:
        gap_ms = self._gap_ms
        bisect.insort(self._passes, p)
        bisect.insort(self._uppers, p.mu_upper)
        times = self._by_vehicle.setdefault(p.vehicle_id, [])
        i = bisect.bisect_right(times, p.time_ms)
        before = times[i - 1] if i else None
        if i < len(times):  # the vehicle's next pass now follows this one instead of `before`
            after = times[i]
            self.independent += new_visit(p.time_ms, after, gap_ms) - new_visit(before, after, gap_ms)
        self.independent += new_visit(before, p.time_ms, gap_ms)
        times.insert(i, p.time_ms)

    def drop_older(self, time_ms: float, *, inclusive: bool = False) -> None:
        """Forget the passes before `time_ms` (and at it, when inclusive): always the oldest ones."""
        cut = (bisect.bisect_right if inclusive else bisect.bisect_left)(self._passes, time_ms, key=_time_of)
        for p in self._passes[:cut]:
            del self._uppers[bisect.bisect_left(self._uppers, p.mu_upper)]
            times = self._by_vehicle[p.vehicle_id]
            del times[0]  # the vehicle's oldest: it counted; its next one becomes the first, which counts
            if times:
                self.independent += not new_visit(p.time_ms, times[0], self._gap_ms)
            else:
                del self._by_vehicle[p.vehicle_id]
            self.independent -= 1
        del self._passes[:cut]

    def clear(self) -> None:
        self.drop_older(math.inf)


def _time_of(p: _LowPass) -> int:
    return p.time_ms


class _Pass(Pass):
    """A pass (passes.py) as the engine judges it: its excited estimates' bounds, its largest proven bound, and where
    its estimates read low and proved grip (rule 9)."""

    __slots__ = ("grip_at", "low_at", "low_ms", "lowers", "proven", "uppers")

    def __init__(self, vehicle_id: str, cell: str, t: int):
        super().__init__(vehicle_id, cell, t)
        self.uppers: list[float] = []
        self.lowers: list[float] = []
        self.proven = 0.0  # the largest mu_proven of its estimates, excited or not
        self.low_at: list[tuple[float, float]] = []  # positions of excited estimates with mu_upper < threshold_mu
        self.low_ms = _NEVER  # ... and the time of the last of them
        self.grip_at: list[tuple[float, float]] = []  # ... of estimates that proved grip >= threshold_mu

    def evidence_ms(self, verdict: str) -> int:
        """The time of what the pass says (rule 2): a low pass's last low reading, when the ice was under the car (its
        later estimates in the cell, on the way out, are not); any other pass's time (passes.py)."""
        return self.low_ms if verdict == LOW and self.low_ms != _NEVER else self.last_ms


class _Warning:
    __slots__ = (
        "action_sequence_number",
        "detection_ms",
        "dry_passes",
        "dry_seen",
        "evidence_ms",
        "last_event",
        "sequence_number",
        "warning_id",
    )

    def __init__(self, warning_id: str, detection_ms: int, action_sequence_number: int, sequence_number: int = 0):
        self.warning_id, self.detection_ms, self.evidence_ms = warning_id, detection_ms, detection_ms
        self.action_sequence_number, self.sequence_number = action_sequence_number, sequence_number
        self.dry_passes = 0
        self.dry_seen: dict[str, int] = {}  # vehicle_id -> the end of its last dry pass counted
        self.last_event: WarningEvent | None = None

    def count_dry(self, finished: _Pass, gap_ms: float) -> None:
        """Count a dry pass that spoke of the place (rule 6). One vehicle's dry passes closer than gap_ms to the one
        before are one visit (passes.py's `new_visit`), counted once, as its low passes are (rule 4): a visit that
        crosses a cell border speaks of the place from both cells (rule 9)."""
        before = self.dry_seen.get(finished.vehicle_id)
        if new_visit(before, finished.first_ms, gap_ms):
            self.dry_passes += 1
        self.dry_seen[finished.vehicle_id] = max(finished.last_ms, _NEVER if before is None else before)


class _CellState:
    __slots__ = ("last_dry_ms", "low_passes", "place", "warning")

    def __init__(self, gap_ms: float):
        self.low_passes = _Evidence(gap_ms)
        self.place = Place()  # where its low evidence lies (rule 9)
        self.last_dry_ms = _NEVER  # the last dry pass that spoke of it
        self.warning: _Warning | None = None


class WarningEngine:
    """Slippery-road warnings from low-friction passes; see the module docstring for the rules."""

    def __init__(
        self,
        resolution: int = 10,
        threshold_mu: float = THRESHOLD_MU,
        min_low_passes: int = MIN_LOW_PASSES,
        min_dry_passes: int = MIN_DRY_PASSES,
        pass_gap_s: float = PASS_GAP_S,
        min_excited_per_pass: int = MIN_EXCITED_PER_PASS,
        validity_s: float = VALIDITY_S,
        station_id: int = 1,
        action_sequence=None,
    ):
        self.resolution = validate_resolution(resolution)
        self.threshold_mu = checks.positive_at_most("threshold_mu", threshold_mu)
        self.min_low_passes = checks.count("min_low_passes", min_low_passes)
        self.min_dry_passes = checks.count("min_dry_passes", min_dry_passes)
        self.pass_gap_s = checks.positive_at_most("pass_gap_s", pass_gap_s)
        self.min_excited_per_pass = checks.count("min_excited_per_pass", min_excited_per_pass)
        self.validity_s = checks.positive_at_most("validity_s", validity_s, MAX_VALIDITY_S)  # a DENM cannot say more
        self.station_id = checks.integer_in("station_id", station_id, 0, 4294967295, "an integer StationID")
        # where a new warning's ActionID sequence number comes from: a callable shared by the engines of one
        # originating station (cluster mode: one per region, numbered by the database), or None: this engine counts
        self.action_sequence = action_sequence
        self._judged: list[_Pass] = []  # the passes closed and not yet applied
        self.passes_ = Passes(self.pass_gap_s, _Pass, self._judged.append)  # the pass rule (passes.py)
        self.open_passes_: dict[str, _Pass] = self.passes_.open  # vehicle_id -> its pass in progress
        self.cell_states_: dict[str, _CellState] = {}
        self.active_cells_: set[str] = set()
        self.next_action_sequence_number_ = 0
        self.late_reports_ = 0  # station reports no newer than the station's last in the cell (rule 8)
        self.last_sweep_ms_ = _NEVER
        self.station_last_ms_: dict[tuple[str, str], int] = {}  # (station source, cell) -> its last report applied

    @property
    def late_rows_(self) -> int:
        """Rows dropped as too late: estimates (rule 1) and station reports (rule 8)."""
        return self.passes_.late_rows + self.late_reports_

    # ------------------------------------------------------------------------------------------------------ public

    def update(self, estimates: Iterable[dict], now_ms: int) -> list[WarningEvent]:
        """Feed estimate rows; the events (raised, refreshed, cancelled, expired) this update caused, in the order
        applied: passes by time, then the expiries at now_ms."""
        now_ms = int(now_ms)
        gap_ms = self.pass_gap_s * 1000.0
        resolution = self.resolution
        threshold = self.threshold_mu
        to_cell = cell_of
        place = self.passes_.row
        for row in in_pass_order(estimates):
            vehicle = row["vehicle_id"]
            t = int(row["timestamp_ms"])
            lat, lon = row["latitude_deg"], row["longitude_deg"]
            current = place(vehicle, to_cell(lat, lon, resolution), t)
            if current is None:  # too late to change a verdict (rule 1)
                continue
            proven = row.get("mu_proven")
            if proven is not None:
                current.proven = max(current.proven, proven)
                if proven >= threshold:
                    current.grip_at.append((lat, lon))
            if row["excited"]:
                lo, hi = row["mu_lower"], row["mu_upper"]
                checks.finite_bounds(f"estimate of vehicle {vehicle!r} at {t}", lo, hi)
                current.lowers.append(lo)
                current.uppers.append(hi)
                if hi < threshold:
                    current.low_at.append((lat, lon))
                    current.low_ms = max(current.low_ms, t)
                elif lo >= threshold:
                    current.grip_at.append((lat, lon))
        self.passes_.close_idle(now_ms)  # no estimate from a vehicle for pass_gap_s: its pass is over
        judged = []
        for finished in self._judged:
            verdict = self.verdict(finished.uppers, finished.lowers, finished.proven)
            if verdict != UNKNOWN:  # changes nothing
                judged.append((finished.evidence_ms(verdict), finished.cell, finished.vehicle_id, finished, verdict))
        self._judged.clear()
        judged.sort(key=operator.itemgetter(0, 1, 2))
        events: list[WarningEvent] = []
        for t, _, _, finished, verdict in judged:
            self._apply(finished, verdict, t, now_ms, events)
        self._expire(now_ms, events)
        if now_ms - self.last_sweep_ms_ >= gap_ms:
            self._sweep(now_ms)
        return events

    def station_evidence(self, rows: Iterable[dict], now_ms: int) -> list[WarningEvent]:
        """Apply roadside stations' evidence rows (rule 8), in order of their time; the events caused, then the
        expiries at now_ms."""
        now_ms = int(now_ms)
        events: list[WarningEvent] = []
        for row in sorted(rows, key=operator.itemgetter("timestamp_ms", "cell", "station_id")):
            source, cell, t = f"station:{row['station_id']}", row["cell"], int(row["timestamp_ms"])
            lo, hi = row["mu_lower"], row["mu_upper"]
            checks.interval(f"evidence of station {row['station_id']!r} at {t}", lo, hi)
            if t <= self.station_last_ms_.get((source, cell), _NEVER):
                self.late_reports_ += 1
                continue
            self.station_last_ms_[(source, cell)] = t
            report = _Pass(source, cell, t)
            report.uppers.append(hi)
            report.lowers.append(lo)
            verdict = LOW if hi < self.threshold_mu else DRY if lo >= self.threshold_mu else UNKNOWN
            if verdict != UNKNOWN:
                self._apply(report, verdict, t, now_ms, events, station=True)
        self._expire(now_ms, events)
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
            state = self._cell(event.cell)
            if state.warning is not None and state.warning.last_event.updated_ms >= event.updated_ms:
                continue
            event = dataclasses.replace(event, spots=tuple(event.spots))  # a list when read back from JSON
            warning = _Warning(
                event.warning_id, event.detection_ms, event.action_sequence_number, event.sequence_number
            )
            warning.evidence_ms = event.evidence_ms
            warning.last_event = event
            state.warning = warning
            n_vehicles = max(1, event.n_vehicles)
            state.low_passes.clear()
            for k in range(max(1, event.n_passes)):
                state.low_passes.add(_LowPass(event.evidence_ms, f"restored-{k % n_vehicles}", event.mu_upper))
            state.place.clear()
            state.place.low(event.spots or (UNKNOWN_PLACE,), event.evidence_ms)
            self.active_cells_.add(event.cell)
            self.next_action_sequence_number_ = max(
                self.next_action_sequence_number_, (event.action_sequence_number + 1) % 65536
            )

    # ----------------------------------------------------------------------------------------------------- passes

    def verdict(self, uppers: list[float], lowers: list[float], proven: float = 0.0) -> str:
        """The verdict of a pass from the mu_upper and mu_lower of its excited estimates and the largest mu_proven of
        all its estimates (rule 2)."""
        judged = len(uppers) >= self.min_excited_per_pass
        if judged and statistics.median(uppers) < self.threshold_mu:
            return LOW
        if proven >= self.threshold_mu or (judged and statistics.median(lowers) >= self.threshold_mu):
            return DRY
        return UNKNOWN

    def _apply(
        self,
        finished: _Pass,
        verdict: str,
        t: int,
        now_ms: int,
        events: list[WarningEvent],
        *,
        station: bool = False,
    ) -> None:
        """Apply a pass judged low or dry (rule 2; a station's report, rule 8) at its evidence time t to its cell (rules
        4-7, 9)."""
        validity_ms = self.validity_s * 1000.0
        state = self._cell(finished.cell)
        warning = None if self._lapsed(finished.cell, state, t, now_ms, events) else state.warning
        place = state.place
        if verdict == DRY:
            if station:  # its whole-cell spot, which only its own cell's place holds (rule 8)
                touched = [finished.cell] if self._shows_dry(finished.cell, finished, {finished.cell}, t) else []
            else:  # its grip reaches the spots of the cells next door too (rule 9)
                grip = reach(spots_of(finished.grip_at)) - spots_of(finished.low_at)
                cells = (finished.cell, *h3.grid_ring(finished.cell, 1))
                touched = [c for c in cells if self._shows_dry(c, finished, grip, t)]
            self._settle(touched, t, now_ms, events)
            return
        if t <= state.last_dry_ms:
            return  # superseded by a later dry pass over its place (rules 4, 9)
        place.low({finished.cell} if station else spots_of(finished.low_at), t)
        horizon = max(now_ms, t) - validity_ms
        state.low_passes.drop_older(horizon)
        state.low_passes.add(_LowPass(t, finished.vehicle_id, statistics.median(finished.uppers)))
        if warning is None:
            if state.low_passes.independent >= self.min_low_passes:
                if self.action_sequence is None:
                    number = self.next_action_sequence_number_
                    self.next_action_sequence_number_ = (number + 1) % 65536
                else:
                    number = self.action_sequence()
                warning = state.warning = _Warning(f"{finished.cell}-{t}", t, number)
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
            mu_upper, n_passes, n_vehicles = evidence.median_mu_upper(), evidence.independent, evidence.n_vehicles
        else:  # a cancellation reports the low-friction evidence the warning had
            previous = warning.last_event
            mu_upper, n_passes, n_vehicles = previous.mu_upper, previous.n_passes, previous.n_vehicles
        latitude_deg, longitude_deg = h3.cell_to_latlng(cell)
        event = WarningEvent(
            warning_id=warning.warning_id,
            cell=cell,
            status=status,
            reason=reason,
            detection_ms=warning.detection_ms,
            updated_ms=max(now_ms, warning.evidence_ms),
            latitude_deg=latitude_deg,
            longitude_deg=longitude_deg,
            mu_upper=mu_upper,
            n_passes=n_passes,
            n_vehicles=n_vehicles,
            sequence_number=warning.sequence_number,
            validity_s=self.validity_s,
            evidence_ms=warning.evidence_ms,
            action_sequence_number=warning.action_sequence_number,
            station_id=self.station_id,
            spots=state.place.keys() if status == ACTIVE else warning.last_event.spots,
        )
        warning.last_event = event
        return event

    def _end(
        self, cell: str, state: _CellState, reason: str, evidence_ms: int, now_ms: int, events: list[WarningEvent]
    ) -> None:
        warning = state.warning
        warning.sequence_number += 1
        warning.evidence_ms = max(warning.evidence_ms, evidence_ms)
        events.append(self._event(cell, state, CANCELLED, reason, now_ms))
        state.warning = None
        self.active_cells_.discard(cell)
        if reason == EXPIRED:
            state.low_passes.clear()  # its evidence is older than validity_s
            state.place.clear()

    def _expire(self, now_ms: int, events: list[WarningEvent]) -> None:
        for cell in sorted(self.active_cells_):
            self._lapsed(cell, self.cell_states_[cell], now_ms, now_ms, events)

    def _lapsed(self, cell: str, state: _CellState, t: float, now_ms: int, events: list[WarningEvent]) -> bool:
        """Whether the cell's warning had lapsed by t (validity_s after its last low pass, rule 7); it then ends
        "expired" at its lapse time."""
        warning = state.warning
        if warning is None:
            return False
        lapse_ms = warning.evidence_ms + self.validity_s * 1000.0
        if t < lapse_ms:
            return False
        self._end(cell, state, EXPIRED, int(lapse_ms), now_ms, events)
        return True

    def _shows_dry(self, cell: str, finished: _Pass, grip: set[str], t: int) -> bool:
        """Whether a dry pass at t, of `cell` or of a cell next door, with grip proven on the spots `grip` speaks of the
        place of `cell` (rule 9): it marks the spots it reaches, and counts as one of its warning's dry passes."""
        state = self.cell_states_.get(cell)
        if state is None or not state.place:
            return False  # no low evidence here
        if not new_visit(state.low_passes.last_of(finished.vehicle_id), finished.first_ms, self.pass_gap_s * 1000.0):
            return False  # the rest of a visit that read low here, split by a cell border (rules 2, 9)
        if not state.place.dry(grip, t, next_door=cell != finished.cell):
            return False  # grip proven elsewhere: nothing of its place (rule 9)
        if state.warning is not None and t > state.warning.detection_ms:
            state.warning.count_dry(finished, self.pass_gap_s * 1000.0)
        return True

    def _settle(self, cells: list[str], t: int, now_ms: int, events: list[WarningEvent]) -> None:
        """After a dry pass at t touched the places of `cells`: clear every place now shown dry (rules 6, 9), theirs
        and, as each clears, its neighbours' that were waiting on the ice next door."""
        validity_ms = self.validity_s * 1000.0
        todo = list(cells)  # a cell is looked at again when a neighbour clears: the chain that held it may be gone
        while todo:
            here = todo.pop()
            state = self.cell_states_.get(here)
            if state is None or not state.place or not state.place.shown_dry():
                continue  # nothing to clear (or cleared already: a cleared place is empty)
            if self._lapsed(here, state, t, now_ms, events):
                continue
            warning = state.warning
            if warning is not None and warning.dry_passes < self.min_dry_passes:
                continue
            next_door = [self.cell_states_[c].place for c in h3.grid_ring(here, 1) if c in self.cell_states_]
            if ice_continues(state.place, next_door, t - validity_ms):
                continue  # its own spots shown dry, but the ice they belong to goes on next door (rule 9)
            dry_ms = max(t, state.place.last_dry_ms())
            state.last_dry_ms = max(state.last_dry_ms, dry_ms)
            state.low_passes.drop_older(dry_ms, inclusive=True)  # the low evidence it held is cleared (rule 6)
            state.place.clear()
            if warning is not None and t > warning.detection_ms:
                self._end(here, state, RECOVERED, t, now_ms, events)
            todo.extend(h3.grid_ring(here, 1))

    def _cell(self, cell: str) -> _CellState:
        state = self.cell_states_.get(cell)
        if state is None:
            state = self.cell_states_[cell] = _CellState(self.pass_gap_s * 1000.0)
        return state

    def _sweep(self, now_ms: int) -> None:
        """Forget cells with no warning whose evidence (low passes, last dry pass) is older than validity_s, and the
        last judged pass of vehicles gone for as long."""
        horizon = now_ms - self.validity_s * 1000.0
        for cell in [c for c, s in self.cell_states_.items() if s.warning is None]:
            state = self.cell_states_[cell]
            state.low_passes.drop_older(horizon)
            state.place.forget(horizon)
            if not state.low_passes and not state.place and state.last_dry_ms < horizon:
                del self.cell_states_[cell]
        self.passes_.forget(horizon)
        for key in [k for k, t in self.station_last_ms_.items() if t < horizon]:
            del self.station_last_ms_[key]
        self.last_sweep_ms_ = now_ms
