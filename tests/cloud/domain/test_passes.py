"""The pass rule (roadgrip/cloud/domain/passes.py) on hand-made rows: a pass ends at a change of cell, after pass_gap_s
without an estimate, or when the clock runs pass_gap_s past it; late rows are dropped and counted. And its two
consumers, the friction map and the warning engine, cut the same rows into the same passes."""

import calendar

import h3
import pytest

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.passes import Pass, Passes, in_pass_order
from roadgrip.cloud.domain.warnings import WarningEngine

T0_MS = calendar.timegm((2026, 1, 15, 8, 0, 0)) * 1000
GAP_S = 30.0


def tracker() -> tuple[Passes, list[tuple[str, str, int, int]]]:
    closed = []
    passes = Passes(GAP_S, Pass, lambda p: closed.append((p.vehicle_id, p.cell, p.first_ms, p.last_ms)))
    return passes, closed


def bounds(p: Pass | None) -> tuple | None:
    return None if p is None else (p.vehicle_id, p.cell, p.first_ms, p.last_ms)


def test_consecutive_rows_in_one_cell_are_one_pass_and_another_cell_ends_it():
    passes, closed = tracker()
    first = passes.row("v", "A", T0_MS)
    assert passes.row("v", "A", T0_MS + 100) is first and passes.row("v", "A", T0_MS + 200) is first
    assert closed == [] and bounds(first) == ("v", "A", T0_MS, T0_MS + 200)
    second = passes.row("v", "B", T0_MS + 300)
    assert closed == [("v", "A", T0_MS, T0_MS + 200)] and bounds(second) == ("v", "B", T0_MS + 300, T0_MS + 300)
    assert passes.open == {"v": second} and passes.late_rows == 0
    assert bounds(passes.row("w", "A", T0_MS + 300)) == ("w", "A", T0_MS + 300, T0_MS + 300)  # vehicles apart
    assert len(closed) == 1


def test_a_pass_ends_after_pass_gap_s_without_an_estimate_in_its_cell_or_at_the_clock():
    passes, closed = tracker()
    first = passes.row("v", "A", T0_MS)
    assert passes.row("v", "A", T0_MS + 30_000) is first  # exactly pass_gap_s: the same pass
    again = passes.row("v", "A", T0_MS + 60_001)  # back more than pass_gap_s later: a new pass in the same cell
    assert again is not first and closed == [("v", "A", T0_MS, T0_MS + 30_000)]
    passes.close_idle(T0_MS + 90_001)
    assert passes.open == {"v": again} and len(closed) == 1  # exactly pass_gap_s idle: still open
    passes.close_idle(T0_MS + 90_002)
    assert passes.open == {} and closed[-1] == ("v", "A", T0_MS + 60_001, T0_MS + 60_001)
    assert passes.closed_ms == {"v": T0_MS + 60_001}


def test_late_rows_are_dropped_and_counted_unless_they_belong_to_the_open_pass():
    passes, closed = tracker()
    a = passes.row("v", "A", T0_MS + 1000)
    assert passes.row("v", "A", T0_MS + 500) is a and a.first_ms == T0_MS + 500  # late, of the open pass: it joins
    b = passes.row("v", "B", T0_MS + 2000)
    assert passes.row("v", "A", T0_MS + 1500) is None  # another cell, older than the open pass's newest: late
    assert passes.row("v", "C", T0_MS + 1999) is None
    assert passes.row("v", "B", T0_MS + 1800) is b and b.first_ms == T0_MS + 1800  # its own pass's cell: joins
    assert passes.row("v", "B", T0_MS + 1000) is None  # no newer than the closed pass in A: too late even here
    assert passes.late_rows == 3 and closed == [("v", "A", T0_MS + 500, T0_MS + 1000)]
    passes.close_idle(T0_MS + 40_000)
    assert passes.row("v", "B", T0_MS + 2000) is None  # its pass is closed: a row of it no longer changes it
    assert passes.late_rows == 4
    c = passes.row("v", "B", T0_MS + 2001)  # newer than every closed pass: a pass of its own
    assert bounds(c) == ("v", "B", T0_MS + 2001, T0_MS + 2001)


def test_a_vehicle_s_last_pass_is_forgotten_when_its_consumer_says_so():
    passes, _ = tracker()
    passes.row("v", "A", T0_MS)
    passes.close_idle(T0_MS + 31_000)
    passes.forget(T0_MS)  # not before the horizon: kept
    assert passes.row("v", "A", T0_MS - 5000) is None and passes.closed_ms == {"v": T0_MS}
    passes.forget(T0_MS + 1)
    assert passes.closed_ms == {}
    assert bounds(passes.row("v", "A", T0_MS - 5000)) == ("v", "A", T0_MS - 5000, T0_MS - 5000)
    passes.forget(T0_MS + 10**9)
    assert "v" in passes.open  # a vehicle with a pass open keeps it


def test_a_resumed_pass_stays_open_unless_the_vehicle_has_a_newer_one():
    passes, closed = tracker()
    newer = passes.row("v", "B", T0_MS + 5000)
    passes.resume(Pass("v", "A", T0_MS))
    assert passes.open == {"v": newer} and closed == [("v", "A", T0_MS, T0_MS)]
    resumed = Pass("v", "C", T0_MS + 9000)
    passes.resume(resumed)
    assert passes.open == {"v": resumed} and closed[-1] == ("v", "B", T0_MS + 5000, T0_MS + 5000)


def test_rows_are_taken_with_a_position_in_vehicle_and_time_order():
    rows = [
        {"vehicle_id": v, "timestamp_ms": t, "latitude_deg": lat, "longitude_deg": 114.5}
        for v, t, lat in (("b", 2, 38.0), ("a", 3, 38.0), ("a", 1, None), ("a", 2, 38.0))
    ]
    assert [(r["vehicle_id"], r["timestamp_ms"]) for r in in_pass_order(rows)] == [("a", 2), ("a", 3), ("b", 2)]


# -------------------------------------------------------------------------------------------- the two consumers

CELL_A = h3.latlng_to_cell(38.0, 114.5, 10)
CELL_B = min(h3.grid_ring(CELL_A, 1))  # a neighbour


def row(t_ms: int, cell: str) -> dict:
    lat, lon = h3.cell_to_latlng(cell)
    return {
        "vehicle_id": "v",
        "timestamp_ms": t_ms,
        "latitude_deg": lat,
        "longitude_deg": lon,
        "mu": 0.25,
        "mu_lower": 0.2,
        "mu_upper": 0.3,
        "excited": True,
        "mu_proven": None,
    }


def test_five_late_rows_give_the_same_passes_in_the_map_and_the_engine():
    """A vehicle drives through cell A, then B; five of its rows in A arrive after those of B. The map once took each
    as a pass of its own (cell A: 1 pass, weight 0.98, became 6 passes, weight 5.87) where the engine dropped them;
    both now drop and count them."""
    through = [row(T0_MS + 100 * k, CELL_A) for k in range(20)] + [
        row(T0_MS + 2000 + 100 * k, CELL_B) for k in range(20)
    ]
    late = [row(T0_MS + 50 + 100 * k, CELL_A) for k in range(5)]
    fmap, engine = FrictionMap(pass_gap_s=GAP_S), WarningEngine(pass_gap_s=GAP_S)
    for rows, now_ms in ((through, T0_MS + 4000), (late, T0_MS + 5000)):
        fmap.add(rows, now_ms)
        engine.update(rows, now_ms)
    assert fmap.late_rows_ == engine.late_rows_ == 5
    assert (
        {v: bounds(p) for v, p in fmap.open_passes_.items()}
        == {v: bounds(p) for v, p in engine.open_passes_.items()}
        == {"v": ("v", CELL_B, T0_MS + 2000, T0_MS + 3900)}
    )
    assert fmap.passes_.closed_ms == engine.passes_.closed_ms == {"v": T0_MS + 1900}
    a = next(c for c in fmap.cells(T0_MS + 20_000) if c.cell == CELL_A)
    assert (a.n_passes, a.n_estimates) == (1, 20)
    assert a.weight == pytest.approx(2.0 ** (-18.1 / 600.0)) and round(a.weight, 2) == 0.98
