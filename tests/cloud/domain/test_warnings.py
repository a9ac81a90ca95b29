"""Slippery-road warnings: which cells are raised (exactly the low-friction cells driven, by enough passes), refreshed,
cancelled by dry passes and expired, and their DENM."""

import dataclasses
import json
import random
import statistics

import h3
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from warning_route import LAT_DEG, LON0_DEG, PATCH, T0_MS, drive

from roadgrip.cloud.domain.warnings import MIN_LOW_PASSES, WarningEngine, WarningEvent, _Evidence, _LowPass
from roadgrip.cloud.formats.denm import ITS_EPOCH_UNIX_MS, denm, timestamp_its_ms


def stream(engine, rows, batch_ms=1000, settle_s=31.0):
    """Feed rows in time order in batches of batch_ms (now = the batch's end), then let the passes close."""
    rows = sorted(rows, key=lambda r: r["timestamp_ms"])
    events, start = [], rows[0]["timestamp_ms"]
    while rows:
        end = start + batch_ms
        batch = [r for r in rows if r["timestamp_ms"] < end]
        rows = rows[len(batch) :]
        events += engine.update(batch, end)
        start = end
    events += engine.update([], start + int(settle_s * 1000))
    return events


def two_pass_engine(**settings) -> WarningEngine:
    """The rules' mechanics with two low passes to raise; the product raises on one (MIN_LOW_PASSES, chosen by the fleet
    benchmark), which `test_the_product_raises_on_one_low_pass` checks."""
    return WarningEngine(**{"min_low_passes": 2, **settings})


def raised(events):
    return {e.cell for e in events if e.status == "active" and e.sequence_number == 0}


def test_a_patch_driven_by_two_vehicles_raises_exactly_its_cells():
    engine = two_pass_engine()
    events = stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    assert raised(events) == PATCH == {e.cell for e in engine.active()}
    assert all(e.status == "active" for e in events)  # nothing cancelled
    for event in engine.active():
        assert event.reason == "low friction" and event.n_passes == 2 and event.n_vehicles == 2
        assert event.mu_upper == pytest.approx(0.3)
        assert event.warning_id == f"{event.cell}-{event.detection_ms}"
        assert h3.latlng_to_cell(event.latitude_deg, event.longitude_deg, 10) == event.cell
        assert T0_MS + 60_000 < event.detection_ms < T0_MS + 130_000  # raised by b's pass


def test_the_product_raises_on_one_low_pass():
    assert WarningEngine().min_low_passes == MIN_LOW_PASSES == 1
    events = stream(WarningEngine(), drive("a", T0_MS))
    assert raised(events) == PATCH  # one vehicle braking on the patch, one low pass in each of its cells


def test_one_pass_of_one_vehicle_raises_nothing():
    engine = two_pass_engine()
    assert stream(engine, drive("a", T0_MS)) == []
    assert engine.active() == []


def test_two_passes_of_one_vehicle_raise_when_apart_by_more_than_the_gap():
    engine = two_pass_engine(pass_gap_s=30.0)
    events = stream(engine, drive("a", T0_MS) + drive("a", T0_MS + 110_000, reverse=True))  # back after 40 s or more
    assert raised(events) == PATCH
    assert all(e.n_vehicles == 1 and e.n_passes == 2 for e in engine.active())


def test_a_pause_shorter_than_the_gap_is_one_pass():
    engine = two_pass_engine(pass_gap_s=30.0)
    rows = drive("a", T0_MS)
    patch_rows = [r for r in rows if h3.latlng_to_cell(r["latitude_deg"], r["longitude_deg"], 10) in PATCH]
    again = [{**r, "timestamp_ms": r["timestamp_ms"] + 20_000} for r in patch_rows[-5:]]  # stood 20 s, went on
    assert stream(engine, rows[: rows.index(patch_rows[-1]) + 1] + again) == []


def test_dry_passes_cancel_the_warning_and_keep_its_action_id():
    engine = two_pass_engine(min_dry_passes=1)
    first = stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    events = stream(engine, drive("c", T0_MS + 300_000, slippery=set()))
    assert {e.cell for e in events} == PATCH and engine.active() == []
    by_id = {e.warning_id: e for e in first}
    for event in events:
        assert (event.status, event.reason) == ("cancelled", "recovered")
        assert event.action_sequence_number == by_id[event.warning_id].action_sequence_number
        assert event.sequence_number == 1
        assert T0_MS + 300_000 < event.evidence_ms < T0_MS + 370_000  # the dry pass
        message = denm(event)
        assert message["denm"]["management"]["termination"] == "isCancellation"
        assert message["denm"]["management"]["actionID"]["sequenceNumber"] == event.action_sequence_number


def test_a_calm_pass_that_proves_grip_is_a_dry_pass():
    engine = two_pass_engine(min_dry_passes=1)
    stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    calm = [
        {**r, "mu": 0.8, "mu_lower": 0.0, "mu_upper": 1.2, "excited": False, "mu_proven": 0.45}
        for r in drive("c", T0_MS + 300_000, slippery=set())
    ]
    events = stream(engine, calm)
    assert {e.cell for e in events} == PATCH and engine.active() == []
    assert {(e.status, e.reason) for e in events} == {("cancelled", "recovered")}


def test_the_verdict_reads_low_before_what_a_sample_proved_and_proof_below_threshold_is_no_verdict():
    engine = two_pass_engine(threshold_mu=0.4, min_excited_per_pass=3)
    assert engine.verdict([0.3, 0.3, 0.3], [0.1, 0.1, 0.1], proven=0.5) == "low"  # a pass across a patch's edge
    assert engine.verdict([], [], proven=0.41) == "dry"
    assert engine.verdict([], [], proven=0.39) == "unknown"
    assert engine.verdict([0.9, 0.9], [0.5, 0.5], proven=0.0) == "unknown"  # too few excited estimates


def test_one_dry_pass_does_not_cancel_when_two_are_needed():
    engine = two_pass_engine(min_dry_passes=2)
    stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    assert stream(engine, drive("c", T0_MS + 300_000, slippery=set())) == []
    events = stream(engine, drive("d", T0_MS + 400_000, slippery=set()))
    assert {e.cell for e in events if e.reason == "recovered"} == PATCH


def test_without_a_refresh_the_warning_expires_after_validity():
    engine = two_pass_engine(validity_s=600.0)
    stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    last_low_ms = {e.cell: e.evidence_ms for e in engine.active()}
    lapse_ms = max(last_low_ms.values()) + 600_000
    assert engine.update([], min(last_low_ms.values()) + 600_000 - 1) == []
    events = engine.update([], lapse_ms)
    assert {e.cell for e in events} == PATCH and engine.active() == []
    for event in events:
        assert (event.status, event.reason) == ("cancelled", "expired")
        assert event.evidence_ms == last_low_ms[event.cell] + 600_000


def test_a_low_pass_refreshes_and_extends_the_warning():
    engine = two_pass_engine(validity_s=600.0)
    first = {e.cell: e for e in stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))}
    refreshed = stream(engine, drive("c", T0_MS + 500_000))
    assert {e.cell for e in refreshed} == PATCH
    for event in refreshed:
        assert event.status == "active" and event.sequence_number == 1
        assert event.warning_id == first[event.cell].warning_id
        assert (event.n_passes, event.n_vehicles) == (3, 3)
        assert denm(event)["denm"]["management"]["detectionTime"] == timestamp_its_ms(event.evidence_ms)
    assert engine.update([], T0_MS + 800_000) == []  # the first evidence alone would have lapsed by now
    assert len(engine.update([], T0_MS + 1_200_000)) == len(PATCH)


def test_low_passes_before_a_dry_one_do_not_count():
    engine = two_pass_engine()
    events = stream(
        engine, drive("a", T0_MS) + drive("c", T0_MS + 100_000, slippery=set()) + drive("b", T0_MS + 200_000)
    )
    assert raised(events) == set()


def test_batching_and_order_do_not_change_the_warnings():
    rows = drive("a", T0_MS) + drive("b", T0_MS + 60_000)
    streamed = stream(two_pass_engine(), rows)
    shuffled = rows[:]
    random.Random(3).shuffle(shuffled)
    at_once = two_pass_engine().update(shuffled, T0_MS + 200_000)
    key = sorted((e.warning_id, e.n_passes, e.mu_upper) for e in streamed)
    assert sorted((e.warning_id, e.n_passes, e.mu_upper) for e in at_once) == key
    # one vehicle's rows slightly late, across batch boundaries (swapped in pairs)
    late = rows[:]
    for i in range(0, len(late) - 1, 2):
        late[i], late[i + 1] = late[i + 1], late[i]
    engine = two_pass_engine()
    events = []
    for start in range(0, len(late), 7):
        batch = late[start : start + 7]
        events += engine.update(batch, max(r["timestamp_ms"] for r in batch))
    events += engine.update([], T0_MS + 200_000)
    assert sorted((e.warning_id, e.n_passes, e.mu_upper) for e in events) == key


def test_rows_without_position_are_ignored():
    rows = [{**r, "latitude_deg": None} for r in drive("a", T0_MS) + drive("b", T0_MS + 60_000)]
    assert stream(two_pass_engine(), rows) == []


def test_restore_brings_back_active_warnings():
    engine = two_pass_engine()
    stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    saved = engine.active()
    restarted = two_pass_engine()
    restarted.restore(saved)
    assert restarted.active() == saved
    events = stream(restarted, drive("c", T0_MS + 300_000, slippery=set()))
    assert {e.warning_id for e in events} == {e.warning_id for e in saved}
    assert all(e.reason == "recovered" for e in events)
    raised_again = stream(restarted, drive("d", T0_MS + 400_000) + drive("e", T0_MS + 470_000))
    assert {e.action_sequence_number for e in raised_again}.isdisjoint({e.action_sequence_number for e in saved})


def test_denm_of_a_raised_warning():
    engine = two_pass_engine(station_id=4242)
    events = stream(engine, drive("a", T0_MS) + drive("b", T0_MS + 60_000))
    event = events[0]
    message = denm(event)
    management = message["denm"]["management"]
    assert message["header"] == {"protocolVersion": 2, "messageID": 1, "stationID": 4242}
    assert message["denm"]["situation"]["eventType"] == {"causeCode": 6, "subCauseCode": 0}
    assert message["denm"]["situation"]["informationQuality"] == 4  # 2 passes, 2 vehicles
    assert "termination" not in management
    assert management["actionID"] == {"originatingStationID": 4242, "sequenceNumber": event.action_sequence_number}
    # 2026 is after the five leap seconds since 2004 (2005-12, 2008-12, 2012-06, 2015-06, 2016-12)
    assert management["detectionTime"] == event.detection_ms - ITS_EPOCH_UNIX_MS + 5000
    assert management["referenceTime"] == event.updated_ms - ITS_EPOCH_UNIX_MS + 5000
    position = management["eventPosition"]
    assert h3.latlng_to_cell(position["latitude"] / 1e7, position["longitude"] / 1e7, 10) == event.cell
    assert management["validityDuration"] == 600 and management["stationType"] == 15
    assert management["relevanceDistance"] == "lessThan100m"
    assert message["roadgrip"]["cell"] == event.cell


@pytest.mark.parametrize(
    ("name", "value"),
    [
        ("resolution", 16),
        ("threshold_mu", 0),
        ("min_low_passes", 0),
        ("min_dry_passes", 1.5),
        ("pass_gap_s", -1),
        ("min_excited_per_pass", True),
        ("validity_s", 86_401),
        ("station_id", -1),
    ],
)
def test_arguments_are_validated(name, value):
    with pytest.raises(ValueError, match=rf"{name}.*{value!r}"):
        WarningEngine(**{name: value})


def test_event_is_frozen():
    event = WarningEvent(
        warning_id="c-1",
        cell=h3.latlng_to_cell(LAT_DEG, LON0_DEG, 10),
        status="active",
        reason="low friction",
        detection_ms=T0_MS,
        updated_ms=T0_MS,
        latitude_deg=LAT_DEG,
        longitude_deg=LON0_DEG,
        mu_upper=0.3,
        n_passes=2,
        n_vehicles=1,
        sequence_number=0,
        validity_s=600.0,
        evidence_ms=T0_MS,
        action_sequence_number=0,
    )
    with pytest.raises(AttributeError):
        event.status = "cancelled"


def test_one_vehicle_in_and_out_of_a_cell_along_its_border_is_one_pass():
    """GNSS noise on a road along a cell border: the vehicle alternates between two icy cells every few samples.
    That is one visit of each cell, however many passes it splits into: no warning from one vehicle."""
    engine = two_pass_engine()
    a, b = sorted(PATCH)[:2]
    (lat_a, lon_a), (lat_b, lon_b) = h3.cell_to_latlng(a), h3.cell_to_latlng(b)
    rows = []
    for i in range(120):
        lat, lon = (lat_a, lon_a) if (i // 5) % 2 == 0 else (lat_b, lon_b)
        rows.append(
            {
                "vehicle_id": "v",
                "timestamp_ms": T0_MS + 100 * i,
                "latitude_deg": lat,
                "longitude_deg": lon,
                "mu": 0.2,
                "mu_lower": 0.1,
                "mu_upper": 0.3,
                "excited": True,
            }
        )
    assert raised(stream(engine, rows)) == set()
    assert raised(
        stream(engine, [{**r, "vehicle_id": "w", "timestamp_ms": r["timestamp_ms"] + 5_000} for r in rows])
    ) == {a, b}


def independent_passes(passes, gap_ms):
    """Rule 4 recounted from scratch: of each vehicle's passes in time order, the first and every one more than
    gap_ms after its predecessor."""
    count, last_by_vehicle = 0, {}
    for p in sorted(passes, key=lambda p: p.time_ms):
        last = last_by_vehicle.get(p.vehicle_id)
        count += last is None or p.time_ms - last > gap_ms
        last_by_vehicle[p.vehicle_id] = p.time_ms
    return count


_operations = st.lists(
    st.one_of(
        st.tuples(st.just("add"), st.integers(0, 600), st.sampled_from("abcd"), st.floats(0.0, 0.4)),
        st.tuples(st.just("drop"), st.integers(0, 600), st.booleans()),
    ),
    max_size=60,
)


@settings(max_examples=300, deadline=None)
@given(_operations)
def test_evidence_kept_up_to_date_equals_a_recount_after_every_change(operations):
    """The cell's evidence updated pass by pass (binary searches) reports what a recount of its passes reports."""
    evidence, passes = _Evidence(gap_ms=30.0), []
    for op in operations:
        if op[0] == "add":
            _, t, vehicle, mu_upper = op
            evidence.add(_LowPass(t, vehicle, mu_upper))
            passes.append(_LowPass(t, vehicle, mu_upper))
        else:
            _, t, inclusive = op
            evidence.drop_older(t, inclusive=inclusive)
            passes = [p for p in passes if (p.time_ms > t if inclusive else p.time_ms >= t)]
        assert len(evidence) == len(passes)
        assert evidence.independent == independent_passes(passes, 30.0)
        assert evidence.n_vehicles == len({p.vehicle_id for p in passes})
        if passes:
            assert evidence.median_mu_upper() == statistics.median(p.mu_upper for p in passes)


# ------------------------------------------------------------------------------------- the place of a warning (rule 9)

CELL = h3.latlng_to_cell(LAT_DEG, LON0_DEG, 10)


def _far_spots():
    """Two resolution-12 spots of CELL as far apart as its children allow (the cell is ~150 m across)."""
    children = sorted(c for c in h3.cell_to_children(CELL, 12) if h3.latlng_to_cell(*h3.cell_to_latlng(c), 10) == CELL)
    pairs = [(a, b) for a in children for b in children if a < b]
    a, b = max(pairs, key=lambda p: h3.great_circle_distance(h3.cell_to_latlng(p[0]), h3.cell_to_latlng(p[1]), "m"))
    return h3.cell_to_latlng(a), h3.cell_to_latlng(b)


ICE_SPOT, OTHER_SPOT = _far_spots()


def at(vehicle, start_ms, spot, *, low, n=20, **extra):
    """n excited estimates, 100 ms apart, within a metre of `spot`: low (mu_upper 0.3) or dry (mu_lower 0.6)."""
    mu, lo, hi = (0.2, 0.1, 0.3) if low else (0.8, 0.6, 0.95)
    return [
        {
            "vehicle_id": vehicle,
            "timestamp_ms": start_ms + 100 * i,
            "latitude_deg": spot[0] + 1e-6 * (i % 5),
            "longitude_deg": spot[1],
            "mu": mu,
            "mu_lower": lo,
            "mu_upper": hi,
            "excited": True,
            **extra,
        }
        for i in range(n)
    ]


def test_the_two_spots_are_in_one_cell_and_far_apart():
    assert h3.latlng_to_cell(*ICE_SPOT, 10) == h3.latlng_to_cell(*OTHER_SPOT, 10) == CELL
    assert h3.great_circle_distance(ICE_SPOT, OTHER_SPOT, "m") > 80.0


def test_a_dry_pass_elsewhere_in_the_cell_neither_cancels_nor_refreshes():
    engine = WarningEngine()
    (raised_event,) = stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    assert raised_event.cell == CELL and raised_event.spots == (h3.latlng_to_cell(*ICE_SPOT, 12),)
    assert stream(engine, at("b", T0_MS + 120_000, OTHER_SPOT, low=False)) == []  # grip proven 80+ m away
    calm = at("c", T0_MS + 240_000, OTHER_SPOT, low=False, excited=False, mu_proven=0.5)
    assert stream(engine, calm) == []
    assert [e.warning_id for e in engine.active()] == [raised_event.warning_id]
    assert engine.active()[0].sequence_number == 0


def test_a_dry_pass_over_the_low_spot_cancels():
    engine = WarningEngine()
    (raised_event,) = stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    stream(engine, at("b", T0_MS + 120_000, OTHER_SPOT, low=False))
    (event,) = stream(engine, at("c", T0_MS + 240_000, ICE_SPOT, low=False))
    assert (event.warning_id, event.status, event.reason) == (raised_event.warning_id, "cancelled", "recovered")
    assert T0_MS + 240_000 <= event.evidence_ms < T0_MS + 242_000
    assert event.spots == raised_event.spots and engine.active() == []


def _spot_beside(spot_latlng):
    """A resolution-12 neighbour of the spot of `spot_latlng`, inside CELL (about 19 m away)."""
    spot = h3.latlng_to_cell(*spot_latlng, 12)
    return h3.cell_to_latlng(
        next(c for c in h3.grid_ring(spot, 1) if h3.latlng_to_cell(*h3.cell_to_latlng(c), 10) == CELL)
    )


def test_grip_beside_a_low_spot_shows_that_spot_dry_and_the_warning_ends_when_every_spot_is():
    """Low read at two places of the cell 80+ m apart: grip proven beside one of them (within about 15-30 m: GNSS error,
    an estimate's window) shows that one dry, not the other; the warning ends when grip is proven at the other too."""
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True) + at("b", T0_MS + 5_000, OTHER_SPOT, low=True))
    assert len(engine.active()[0].spots) == 2
    assert stream(engine, at("c", T0_MS + 120_000, _spot_beside(ICE_SPOT), low=False)) == []
    assert engine.cell_states_[CELL].place.keys() == (h3.latlng_to_cell(*OTHER_SPOT, 12),)  # not yet shown dry
    (event,) = stream(engine, at("d", T0_MS + 240_000, OTHER_SPOT, low=False))
    assert event.reason == "recovered"


def test_a_pass_skirting_the_low_place_does_not_cancel_and_one_over_it_does():
    """Synthetic passes along a line through CELL: a vehicle reads low over 40 m (three spots in a row); a later one
    proves grip only at one end of that stretch (it braked where the patch begins and was calm over it): the rest of the
    place is not shown dry and the warning stays; a vehicle braking over the whole stretch ends it."""
    engine = WarningEngine()
    first = h3.latlng_to_cell(*ICE_SPOT, 12)
    row = [first]
    while len(row) < 4:  # four spots in a line of neighbours, all in CELL, away from OTHER_SPOT
        row.append(
            next(
                c
                for c in h3.grid_ring(row[-1], 1)
                if c not in row
                and h3.latlng_to_cell(*h3.cell_to_latlng(c), 10) == CELL
                and all(h3.grid_distance(c, r) >= 2 for r in row[:-1])
            )
        )
    positions = [h3.cell_to_latlng(c) for c in row]
    low = [r for k, p in enumerate(positions) for r in at("a", T0_MS + 2_000 * k, p, low=True, n=10)]
    stream(engine, low)
    assert len(engine.active()[0].spots) == 4
    assert stream(engine, at("b", T0_MS + 120_000, positions[0], low=False)) == []  # grip at one end only
    assert engine.active(), "grip proven at the place's edge ended the warning"
    over = [r for k, p in enumerate(positions) for r in at("c", T0_MS + 240_000 + 2_000 * k, p, low=False, n=10)]
    (event,) = stream(engine, over)
    assert event.reason == "recovered"


def test_a_pass_that_reads_low_on_the_place_and_grip_beyond_it_does_not_cancel():
    """A pass that crosses the patch's edge: low readings on the place, then grip on the dry road past it, more of
    them than the low ones (its verdict by the medians is dry). Its grip beside the place says nothing of where the
    same pass read low."""
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    beside = _spot_beside(ICE_SPOT)
    crossing = at("b", T0_MS + 120_000, ICE_SPOT, low=True, n=8) + at("b", T0_MS + 121_000, beside, low=False, n=20)
    assert stream(engine, crossing) == []
    assert engine.active(), "grip past the edge cancelled a place the same pass read low"


def test_one_dry_pass_over_the_place_does_not_cancel_when_two_are_needed():
    engine = WarningEngine(min_dry_passes=2)
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    assert stream(engine, at("b", T0_MS + 120_000, ICE_SPOT, low=False)) == []
    assert stream(engine, at("c", T0_MS + 240_000, OTHER_SPOT, low=False)) == []  # elsewhere: does not count
    (event,) = stream(engine, at("d", T0_MS + 360_000, ICE_SPOT, low=False))
    assert event.reason == "recovered"


def test_one_vehicles_dry_passes_closer_than_the_gap_are_one_visit():
    """A vehicle over the place, a second in another cell, back over the place: two dry passes of one visit, which
    count once when two are needed; another vehicle's dry pass is the second."""
    engine = WarningEngine(min_dry_passes=2, pass_gap_s=30.0)
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    elsewhere = (ICE_SPOT[0] + 0.01, ICE_SPOT[1])  # about 1 km north: another cell, not next door
    visit = [
        *at("b", T0_MS + 120_000, ICE_SPOT, low=False),
        *at("b", T0_MS + 122_000, elsewhere, low=False, n=5),
        *at("b", T0_MS + 123_000, ICE_SPOT, low=False),
    ]
    assert stream(engine, visit) == []
    (event,) = stream(engine, at("c", T0_MS + 240_000, ICE_SPOT, low=False))
    assert event.reason == "recovered"


def test_a_warning_whose_place_is_never_shown_dry_expires():
    engine = WarningEngine(validity_s=600.0)
    (raised_event,) = stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    stream(engine, at("b", T0_MS + 300_000, OTHER_SPOT, low=False))
    (event,) = engine.update([], raised_event.evidence_ms + 600_000)
    assert (event.reason, event.evidence_ms) == ("expired", raised_event.evidence_ms + 600_000)


def test_restore_keeps_the_place():
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    saved = [WarningEvent(**{**dataclasses.asdict(e), "spots": list(e.spots)}) for e in engine.active()]  # as JSON
    restarted = WarningEngine()
    restarted.restore(saved)
    assert restarted.active()[0].spots == engine.active()[0].spots
    assert stream(restarted, at("b", T0_MS + 120_000, OTHER_SPOT, low=False)) == []
    (event,) = stream(restarted, at("c", T0_MS + 240_000, ICE_SPOT, low=False))
    assert event.reason == "recovered"


def test_an_event_stored_without_its_place_is_cancelled_by_any_dry_pass_in_the_cell():
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, ICE_SPOT, low=True))
    old = [dataclasses.replace(e, spots=()) for e in engine.active()]  # stored before warnings kept their place
    restarted = WarningEngine()
    restarted.restore(old)
    (event,) = stream(restarted, at("b", T0_MS + 120_000, OTHER_SPOT, low=False))
    assert event.reason == "recovered"


def _station_row(station_id, t_ms, mu_lower, mu_upper):
    return {
        "station_id": station_id,
        "cell": CELL,
        "timestamp_ms": t_ms,
        "mu": mu_upper,
        "mu_lower": mu_lower,
        "mu_upper": mu_upper,
    }


def test_a_station_speaks_for_the_whole_cell_and_a_vehicle_for_its_track():
    engine = WarningEngine()
    (raised_event,) = engine.station_evidence([_station_row("rws", T0_MS, 0.05, 0.3)], T0_MS)
    assert raised_event.spots == (CELL,)
    assert stream(engine, at("b", T0_MS + 60_000, ICE_SPOT, low=False)) == []  # grip on one track only
    (event,) = engine.station_evidence([_station_row("rws", T0_MS + 120_000, 0.7, 1.2)], T0_MS + 120_000)
    assert event.reason == "recovered"
    # a vehicle's low spot: the station's dry report (its row holds the cell, not where it stands) says nothing of it
    stream(engine, at("c", T0_MS + 200_000, ICE_SPOT, low=True))
    assert engine.station_evidence([_station_row("rws", T0_MS + 300_000, 0.7, 1.2)], T0_MS + 300_000) == []
    (event,) = stream(engine, at("d", T0_MS + 400_000, ICE_SPOT, low=False))
    assert event.reason == "recovered"


def test_a_late_low_pass_is_superseded_by_a_dry_pass_over_the_place_only():
    engine = two_pass_engine()
    stream(engine, at("a", T0_MS, OTHER_SPOT, low=True) + at("d", T0_MS + 60_000, ICE_SPOT, low=False))
    assert engine.cell_states_[CELL].low_passes  # d proved grip away from a's low reading: a still counts
    (event,) = engine.update(at("b", T0_MS + 30_000, OTHER_SPOT, low=True), T0_MS + 200_000)
    assert event.n_passes == 2 and event.spots == (h3.latlng_to_cell(*OTHER_SPOT, 12),)
    engine = two_pass_engine()
    stream(engine, at("a", T0_MS, OTHER_SPOT, low=True) + at("d", T0_MS + 60_000, OTHER_SPOT, low=False))
    assert engine.update(at("b", T0_MS + 30_000, OTHER_SPOT, low=True), T0_MS + 200_000) == []  # older than d


def test_grip_on_the_way_out_of_the_ice_is_the_rest_of_a_low_visit():
    """A vehicle reads low, crosses a cell border for a moment (GNSS noise) and proves grip just past the patch's edge:
    the same visit, judged low; another vehicle's grip there later cancels."""
    engine = WarningEngine()
    out = h3.cell_to_latlng(h3.grid_ring(CELL, 1)[0])
    rows = at("a", T0_MS, ICE_SPOT, low=True) + at("a", T0_MS + 2_000, out, low=False, n=2)
    rows += at("a", T0_MS + 2_200, ICE_SPOT, low=False, n=5)
    assert raised(stream(engine, rows)) == {CELL}
    assert [e.cell for e in engine.active()] == [CELL]
    (event,) = stream(engine, at("b", T0_MS + 120_000, ICE_SPOT, low=False))
    assert event.reason == "recovered"


# ------------------------------------------- validity from the last low reading; the ice next door (rules 7, 9)


def test_validity_counts_from_the_last_low_reading_not_the_pass_end():
    """A vehicle reads ice for 2 s, then drives on in the cell calmly for 20 s (no verdict in those estimates): the ice
    was under it when it read low, so the warning's evidence, and its validity, count from there."""
    engine = WarningEngine(validity_s=600.0)
    low = at("a", T0_MS, ICE_SPOT, low=True)
    calm = [
        {**r, "mu": 0.8, "mu_lower": 0.0, "mu_upper": 1.2, "excited": False, "mu_proven": 0.1}
        for r in at("a", T0_MS + 2_000, OTHER_SPOT, low=False, n=200)
    ]
    (event,) = stream(engine, low + calm)
    last_low_ms = low[-1]["timestamp_ms"]
    assert event.detection_ms == event.evidence_ms == last_low_ms < calm[-1]["timestamp_ms"] - 19_000
    assert engine.update([], last_low_ms + 600_000 - 1) == []
    (ended,) = engine.update([], last_low_ms + 600_000)
    assert (ended.reason, ended.evidence_ms) == ("expired", last_low_ms + 600_000)


NEXT_DOOR = min(h3.grid_ring(CELL, 1))


def _spots_of_cell(cell):
    """The resolution-12 spots whose estimates by `at` all lie in `cell`."""

    def inside(spot):
        lat, lon = h3.cell_to_latlng(spot)
        return all(h3.latlng_to_cell(lat + 1e-6 * k, lon, 10) == cell for k in range(5))

    return sorted(c for c in h3.grid_disk(h3.cell_to_center_child(cell, 12), 8) if inside(c))


def _ice_across_the_border():
    """Spots of a patch across the border of CELL and NEXT_DOOR: RIM, the spot of CELL nearest NEXT_DOOR; NEAR, a spot
    of NEXT_DOOR beside it; INNER, a spot of NEXT_DOOR further in (within 2 rings of NEAR, 3 from RIM); FAR, the spot of
    NEXT_DOOR furthest from RIM (other ice)."""
    here, there = _spots_of_cell(CELL), _spots_of_cell(NEXT_DOOR)
    rim = min(here, key=lambda s: h3.great_circle_distance(h3.cell_to_latlng(s), h3.cell_to_latlng(NEXT_DOOR), "m"))
    near = next(s for s in there if h3.grid_distance(rim, s) == 1)
    inner = next(s for s in there if h3.grid_distance(rim, s) == 3 and h3.grid_distance(near, s) <= 2)
    far = max(there, key=lambda s: h3.grid_distance(rim, s))
    return tuple(h3.cell_to_latlng(s) for s in (rim, near, inner, far))


RIM, NEAR, INNER, FAR = _ice_across_the_border()


def test_the_ice_across_the_border_lies_as_described():
    assert h3.latlng_to_cell(*RIM, 10) == CELL
    assert {h3.latlng_to_cell(*p, 10) for p in (NEAR, INNER, FAR)} == {NEXT_DOOR}
    assert h3.great_circle_distance(RIM, INNER, "m") > 40.0  # beyond the reach of grip proven on the rim
    assert h3.grid_distance(*(h3.latlng_to_cell(*p, 12) for p in (RIM, FAR))) >= 5  # no chain links them


def _low_across_the_border(engine):
    """A vehicle brakes across the patch: ice read on the rim of CELL, then on two spots of NEXT_DOOR (two passes, one
    low in each cell; the product raises on one)."""
    rows = at("a", T0_MS, RIM, low=True, n=10) + at("a", T0_MS + 1_000, NEAR, low=True, n=10)
    rows += at("a", T0_MS + 2_000, INNER, low=True, n=10)
    events = stream(engine, rows)
    assert raised(events) == {CELL, NEXT_DOOR}
    return {e.cell: e for e in events}


def test_grip_on_the_rim_does_not_end_a_warning_whose_ice_goes_on_next_door():
    """The cell holds only the patch's rim: grip proven on that spot while the ice goes on next door is not the patch
    drying. The same ice shown dry next door (a vehicle braking over it) ends both: a drying road still ends."""
    engine = WarningEngine()
    first = _low_across_the_border(engine)
    assert stream(engine, at("c", T0_MS + 120_000, RIM, low=False)) == []
    assert [(e.cell, e.sequence_number) for e in engine.active()] == sorted([(CELL, 0), (NEXT_DOOR, 0)])
    assert engine.active() == [first[c] for c in sorted(first)]  # neither refreshed nor changed
    over = at("d", T0_MS + 240_000, NEAR, low=False, n=10) + at("d", T0_MS + 241_000, INNER, low=False, n=10)
    events = stream(engine, over)
    assert {(e.cell, e.status, e.reason) for e in events} == {
        (CELL, "cancelled", "recovered"),
        (NEXT_DOOR, "cancelled", "recovered"),
    }
    assert {e.evidence_ms for e in events} == {over[-1]["timestamp_ms"]}  # when the last of the ice was shown dry
    assert engine.active() == []


def test_grip_at_the_border_next_door_does_not_end_it_while_the_ice_further_in_stays():
    """Grip proven on the rim and on the spot beside it next door, not where the ice was read further in: the chain of
    the ice's spots next door still reaches ice, and the warning stays."""
    engine = WarningEngine()
    _low_across_the_border(engine)
    assert stream(engine, at("c", T0_MS + 120_000, NEAR, low=False, n=10)) == []
    assert stream(engine, at("e", T0_MS + 180_000, RIM, low=False)) == []
    assert {e.cell for e in engine.active()} == {CELL, NEXT_DOOR}


def test_other_ice_next_door_does_not_hold_a_warning_shown_dry():
    """Ice read next door far from the cell's place (no chain of spots within reach of each other) is other ice: grip
    on the cell's place ends its warning, and the other one stays."""
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, RIM, low=True) + at("b", T0_MS + 10_000, FAR, low=True))
    assert {e.cell for e in engine.active()} == {CELL, NEXT_DOOR}
    (event,) = stream(engine, at("c", T0_MS + 120_000, RIM, low=False))
    assert (event.cell, event.reason) == (CELL, "recovered")
    assert [e.cell for e in engine.active()] == [NEXT_DOOR]


def test_ice_next_door_raises_nothing_and_holds_a_warning_no_longer_than_its_validity():
    """Low evidence next door never warns a cell without low passes of its own, and holding a warning shown dry never
    makes it outlast its own validity: it expires validity_s after its last low reading."""
    engine = WarningEngine(validity_s=600.0)
    (next_door,) = stream(engine, at("a", T0_MS, NEAR, low=True) + at("a", T0_MS + 2_000, INNER, low=True))
    assert next_door.cell == NEXT_DOOR and [e.cell for e in engine.active()] == [NEXT_DOOR]
    (here,) = stream(engine, at("b", T0_MS + 100_000, RIM, low=True))
    assert stream(engine, at("c", T0_MS + 200_000, RIM, low=False)) == []  # held by the ice next door
    refreshed = stream(engine, at("d", T0_MS + 500_000, INNER, low=True))  # the ice next door read again
    assert [e.cell for e in refreshed] == [NEXT_DOOR]
    (ended,) = engine.update([], here.evidence_ms + 600_000)
    assert (ended.cell, ended.reason, ended.evidence_ms) == (CELL, "expired", here.evidence_ms + 600_000)


def _stored_and_restored(engine):
    """A fresh engine that knows `engine`'s warnings only as the store keeps them (their latest events, read back from
    JSON), as a cluster worker that takes a region over does (roadgrip/cloud/cluster/regions.py)."""
    restarted = WarningEngine()
    restarted.restore(WarningEvent(**json.loads(json.dumps(dataclasses.asdict(e)))) for e in engine.active())
    assert restarted.active() == engine.active()
    return restarted


@pytest.mark.parametrize("restored", [False, True], ids=["same engine", "restored"])
def test_grip_proven_on_ice_read_next_door_shows_it_dry_from_either_cell(restored):
    """The ice's last readings fell just across the border (RIM in CELL, NEAR next door, one spot apart), and a vehicle
    braking over the whole patch proves grip on both spots from CELL alone (its estimates all lie in CELL): both places
    are shown dry and both warnings end. Grip is proven where the tires were, whichever cell a pass is counted in; were
    NEAR shown dry only by a pass in NEXT_DOOR, it would hold CELL's warning as ice next door until it expired."""
    engine = WarningEngine()
    stream(engine, at("a", T0_MS, RIM, low=True, n=10) + at("a", T0_MS + 1_000, NEAR, low=True, n=10))
    assert {e.cell for e in engine.active()} == {CELL, NEXT_DOOR}
    if restored:
        engine = _stored_and_restored(engine)
    over = at("c", T0_MS + 120_000, RIM, low=False)
    assert {h3.latlng_to_cell(r["latitude_deg"], r["longitude_deg"], 10) for r in over} == {CELL}
    events = stream(engine, over)
    assert {(e.cell, e.status, e.reason) for e in events} == {
        (CELL, "cancelled", "recovered"),
        (NEXT_DOOR, "cancelled", "recovered"),
    }
    assert engine.active() == []


def test_restored_warnings_stay_while_the_ice_goes_on_next_door_and_end_when_it_is_shown_dry():
    """The converse, with the warnings restored as a worker that takes a region over knows them
    (test_grip_on_the_rim_does_not_end_a_warning_whose_ice_goes_on_next_door in one engine): grip proven on the rim ends
    nothing while INNER, next door, is not shown dry; grip over the ice next door then ends both."""
    engine = WarningEngine()
    _low_across_the_border(engine)
    engine = _stored_and_restored(engine)
    assert stream(engine, at("c", T0_MS + 120_000, RIM, low=False)) == []
    assert {e.cell for e in engine.active()} == {CELL, NEXT_DOOR}
    over = at("d", T0_MS + 240_000, NEAR, low=False, n=10) + at("d", T0_MS + 241_000, INNER, low=False, n=10)
    events = stream(engine, over)
    assert {(e.cell, e.reason) for e in events} == {(CELL, "recovered"), (NEXT_DOOR, "recovered")}
