"""The DENM as UPER (roadgrip/cloud/formats/denm.py): every kind of message the warning engine makes (new, update,
cancellation after dry passes, cancellation on expiry) decodes from UPER equal to what `denm` rendered; values at the
ends of their ASN.1 ranges too; a value outside its range and malformed bytes are errors; the framing of many."""

import dataclasses

import h3
import pytest
from warning_route import PATCH, T0_MS, drive

from roadgrip.cloud.domain.warnings import MAX_VALIDITY_S, WarningEngine
from roadgrip.cloud.formats.denm import DENM_MEMBERS, decode_denm_uper, denm, denm_uper, frame, unframe


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
    return events + engine.update([], start + int(settle_s * 1000))


def kind(event) -> str:
    if event.status == "active":
        return "update" if event.sequence_number else "new"
    return f"cancellation ({event.reason})"


def engine_events() -> list:
    """The warning engine's events on the test route: raised, refreshed, cancelled by a dry pass; and in a second
    engine raised, then expired."""
    engine = WarningEngine(min_dry_passes=1, station_id=4_000_000_000)
    events = stream(engine, drive("a", T0_MS))  # one low pass raises (the product's setting)
    events += stream(engine, drive("b", T0_MS + 60_000))  # a second low pass refreshes
    events += stream(engine, drive("c", T0_MS + 300_000, slippery=set()))  # a dry pass cancels
    lapsing = WarningEngine(validity_s=600.0)
    events += stream(lapsing, drive("d", T0_MS))
    events += lapsing.update([], T0_MS + 3_600_000)  # not refreshed: expired
    return events


def the_denm(message: dict) -> dict:
    return {name: message[name] for name in DENM_MEMBERS}


def test_every_kind_of_denm_decodes_from_uper_equal_to_what_was_sent():
    events = engine_events()
    by_kind = {}
    for event in events:
        by_kind.setdefault(kind(event), []).append(event)
    assert sorted(by_kind) == ["cancellation (expired)", "cancellation (recovered)", "new", "update"]
    assert {e.cell for e in by_kind["new"]} >= PATCH
    for event in events:
        sent = denm(event)
        encoded = denm_uper(sent)
        assert isinstance(encoded, bytes) and 30 <= len(encoded) <= 60  # about 46 bytes
        back = decode_denm_uper(encoded)
        assert back == the_denm(sent), kind(event)
        assert back["header"]["stationID"] == event.station_id
        assert ("termination" in back["denm"]["management"]) == (event.status == "cancelled")
    # an update and its cancellation keep the event's ActionID, and say so on the wire
    for warning in by_kind["cancellation (recovered)"]:
        raised = next(e for e in by_kind["new"] if e.warning_id == warning.warning_id)
        decoded = [decode_denm_uper(denm_uper(denm(e))) for e in (raised, warning)]
        assert decoded[0]["denm"]["management"]["actionID"] == decoded[1]["denm"]["management"]["actionID"]
        assert decoded[1]["denm"]["management"]["termination"] == "isCancellation"


def test_values_at_the_ends_of_their_ranges_round_trip():
    [event] = [e for e in engine_events() if kind(e) == "new"][:1]
    far_north = h3.latlng_to_cell(89.9, 179.9, 0)  # a cell of hundreds of km: over10km, a large confidence
    lat, lon = h3.cell_to_latlng(far_north)
    for edge in (
        dataclasses.replace(event, station_id=0, action_sequence_number=0, validity_s=0.0),
        dataclasses.replace(event, station_id=4_294_967_295, action_sequence_number=65_535, validity_s=MAX_VALIDITY_S),
        dataclasses.replace(event, cell=far_north, latitude_deg=lat, longitude_deg=lon, n_passes=50, n_vehicles=9),
        dataclasses.replace(event, cell=h3.latlng_to_cell(-33.9, -70.6, 15), latitude_deg=-33.9, longitude_deg=-70.6),
    ):
        sent = denm(edge)
        assert decode_denm_uper(denm_uper(sent)) == the_denm(sent)


def test_a_value_outside_its_asn1_range_or_a_missing_member_is_an_error():
    [event] = [e for e in engine_events() if kind(e) == "new"][:1]
    message = denm(dataclasses.replace(event, station_id=4_294_967_296))  # StationID is 0..4294967295
    with pytest.raises(ValueError, match="ETSI ASN.1"):
        denm_uper(message)
    with pytest.raises(ValueError, match="missing"):
        denm_uper({"header": message["header"]})
    encoded = denm_uper(denm(event))
    with pytest.raises(ValueError, match="not a UPER-encoded DENM"):
        decode_denm_uper(encoded[:10])


def test_framed_denms_come_apart_as_they_went_in():
    encoded = [denm_uper(denm(e)) for e in engine_events()[:5]]
    body = frame(encoded)
    assert len(body) == sum(4 + len(m) for m in encoded)
    assert unframe(body) == encoded
    assert unframe(b"") == [] == unframe(frame([]))
    with pytest.raises(ValueError, match="overruns"):
        unframe(body[:-1])
    with pytest.raises(ValueError, match="cut short"):
        unframe(body + b"\x00\x00")
