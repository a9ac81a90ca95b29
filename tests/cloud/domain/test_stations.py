"""Roadside station reports (roadgrip/cloud/domain/stations.py): the format's validation, the covered cells, and the friction
evidence a report gives (ice reads low, dry reads high, intervals ordered and inside [0, 1.2]), and that evidence
read back from a stored report (SQLite and PostgreSQL)."""

from __future__ import annotations

import itertools
import json

import h3
import pytest

from roadgrip.cloud.domain.stations import (
    COVERAGE_RADIUS_M,
    MAX_REPORTS_PER_PAYLOAD,
    MU_MAX,
    SURFACE_STATES,
    ReportError,
    StationReport,
    covered_cells,
    evidence,
    evidence_rows,
    parse_reports,
    stored_evidence_rows,
    stored_rows,
)
from roadgrip.cloud.domain.warnings import THRESHOLD_MU

NOW_MS = 1_765_000_000_000
REPORT = {
    "station_id": "rws-a9-km12",
    "timestamp_ms": NOW_MS - 30_000,
    "latitude_deg": 48.137,
    "longitude_deg": 11.575,
    "surface_state": "ice",
    "surface_temperature_c": -4.5,
    "water_film_thickness_mm": 0.0,
}


def parse(payload, station_id: str = "rws-a9-km12") -> list[StationReport]:
    return parse_reports(json.dumps(payload).encode(), station_id=station_id, now_ms=NOW_MS)


def refused(payload, station_id: str = "rws-a9-km12") -> ReportError:
    with pytest.raises(ReportError) as caught:
        parse(payload, station_id)
    return caught.value


def test_a_valid_report_and_an_array_of_them_parse():
    [report] = parse(REPORT)
    assert report.surface_state == "ice" and report.surface_temperature_c == -4.5 and report.friction is None
    reports = parse(
        [
            REPORT,
            {**REPORT, "timestamp_ms": NOW_MS, "surface_state": "wet", "friction": 0.55, "friction_uncertainty": 0.08},
        ]
    )
    assert [r.surface_state for r in reports] == ["ice", "wet"] and reports[1].friction_uncertainty == 0.08
    assert parse({**REPORT, "timestamp_ms": float(NOW_MS)})[0].timestamp_ms == NOW_MS  # 1.7e12 written as a float
    minimal = {k: REPORT[k] for k in ("station_id", "timestamp_ms", "latitude_deg", "longitude_deg", "surface_state")}
    assert parse(minimal)[0].water_film_thickness_mm is None


@pytest.mark.parametrize(
    ("change", "field", "says"),
    [
        ({"surface_state": "slush"}, "surface_state", "'dry', 'moist', 'wet', 'ice', 'snow' or 'unknown'"),
        ({"surface_temperature_c": "cold"}, "surface_temperature_c", "valid number"),
        ({"surface_temperature_c": True}, "surface_temperature_c", "valid number"),
        ({"surface_temperature_c": -80}, "surface_temperature_c", "greater than or equal to -60"),
        ({"water_film_thickness_mm": -0.1}, "water_film_thickness_mm", "greater than or equal to 0"),
        ({"friction": 1.3}, "friction", "less than or equal to 1"),
        ({"friction": 0.4, "friction_uncertainty": 0.0}, "friction_uncertainty", "greater than 0"),
        ({"friction_uncertainty": 0.1}, "friction_uncertainty", "given without friction"),
        ({"latitude_deg": 91.0}, "latitude_deg", "less than or equal to 90"),
        ({"timestamp_ms": 1.5}, "timestamp_ms", "valid integer"),
        ({"timestamp_ms": NOW_MS + 61_000}, "timestamp_ms", "ahead of the server's clock"),
        ({"station_id": "rws-other"}, "station_id", "the station of the credentials"),
        ({"waterfilm_thickness_mm": 0.1}, "waterfilm_thickness_mm", "did you mean 'water_film_thickness_mm'"),
    ],
)
def test_a_bad_field_is_refused_with_its_name_and_why(change, field, says):
    error = refused({**REPORT, **change})
    assert (error.index, error.field, error.status) == (0, field, 422)
    assert says in error.reason and field in str(error)


def test_missing_fields_nan_and_payload_shape_are_refused():
    missing = refused({k: v for k, v in REPORT.items() if k != "surface_state"})
    assert missing.field == "surface_state" and "required" in missing.reason.lower()
    body = json.dumps(REPORT).replace("-4.5", "NaN").encode()
    nan = pytest.raises(ReportError, parse_reports, body, station_id="rws-a9-km12", now_ms=NOW_MS).value
    assert nan.field == "surface_temperature_c" and "finite" in nan.reason
    second = refused([REPORT, {**REPORT, "surface_state": "black ice"}])
    assert (second.index, second.field) == (1, "surface_state")  # the whole payload is refused, naming the report
    assert refused([]).reason == "an empty array holds no report"
    assert refused([REPORT] * (MAX_REPORTS_PER_PAYLOAD + 1)).status == 413
    assert refused(["ice"]).reason == "a report is a JSON object, got str"
    bad_json = pytest.raises(ReportError, parse_reports, b"{surface", station_id="x", now_ms=NOW_MS).value
    assert bad_json.status == 400


def test_covered_cells_are_the_stations_cell_and_those_within_the_radius():
    for lat, lon in ((48.137, 11.575), (60.17, 24.94), (-33.87, 151.21)):
        cells = covered_cells(lat, lon, 10)
        own = h3.latlng_to_cell(lat, lon, 10)
        assert own in cells and len(cells) <= 4
        for cell in cells:
            assert (
                cell == own or h3.great_circle_distance((lat, lon), h3.cell_to_latlng(cell), "m") <= COVERAGE_RADIUS_M
            )
        wide = covered_cells(lat, lon, 10, radius_m=400.0)
        assert set(cells) < set(wide) and len(wide) >= 7


def test_ice_reads_low_and_dry_reads_high_whatever_the_other_fields():
    for temperature, film in itertools.product((None, -8.0, -0.5, 2.0), (None, 0.0, 0.5, 3.0)):
        fields = {**REPORT, "surface_temperature_c": temperature, "water_film_thickness_mm": film}
        ice = evidence(StationReport(**{**fields, "surface_state": "ice"}))
        assert ice.mu_upper < THRESHOLD_MU  # a warning-grade low: even its optimistic bound is slippery
        snow = evidence(StationReport(**{**fields, "surface_state": "snow"}))
        assert snow.mu_lower < THRESHOLD_MU and snow.mu <= 0.35
        dry = evidence(StationReport(**{**fields, "surface_state": "dry"}))
        assert dry.mu_lower >= THRESHOLD_MU and dry.mu_upper >= 1.17  # Burckhardt dry asphalt inside
    assert evidence(StationReport(**{**REPORT, "friction": 0.12})).mu_upper == pytest.approx(0.22)
    assert evidence(StationReport(**{**REPORT, "surface_state": "dry", "friction": 0.8})).mu_lower >= THRESHOLD_MU


def test_intervals_are_ordered_inside_0_and_1_2_and_a_thicker_film_never_reads_higher():
    for state, temperature, film, friction in itertools.product(
        SURFACE_STATES, (None, -5.0, 0.0, 5.0), (None, 0.0, 0.2, 0.5, 1.0, 4.0), (None, 0.0, 0.05, 0.5, 0.95, 1.0)
    ):
        found = evidence(
            StationReport(
                **{
                    **REPORT,
                    "surface_state": state,
                    "surface_temperature_c": temperature,
                    "water_film_thickness_mm": film,
                    "friction": friction,
                }
            )
        )
        if state == "unknown" and friction is None:
            assert found is None  # says nothing about grip
            continue
        assert 0.0 <= found.mu_lower <= found.mu <= found.mu_upper <= MU_MAX
        assert found.mu_upper - found.mu_lower >= 0.2 - 1e-12 or friction is not None  # a class, not a measurement
    wet = [
        evidence(
            StationReport(
                **{**REPORT, "surface_state": "wet", "surface_temperature_c": 5.0, "water_film_thickness_mm": film}
            )
        )
        for film in (0.1, 0.5, 3.0)
    ]
    assert [e.mu for e in wet] == sorted((e.mu for e in wet), reverse=True)
    assert [e.mu_upper for e in wet] == sorted((e.mu_upper for e in wet), reverse=True)


def test_a_wet_road_below_freezing_is_an_ice_risk_neither_dry_nor_warned_alone():
    warm = evidence(
        StationReport(
            **{**REPORT, "surface_state": "wet", "surface_temperature_c": 3.0, "water_film_thickness_mm": 0.1}
        )
    )
    freezing = evidence(
        StationReport(
            **{**REPORT, "surface_state": "wet", "surface_temperature_c": -1.0, "water_film_thickness_mm": 0.1}
        )
    )
    assert warm.mu_lower >= THRESHOLD_MU  # grip proven on a warm wet road
    assert freezing.mu_lower <= 0.05 and freezing.mu_upper == warm.mu_upper and freezing.mu < warm.mu
    assert not freezing.mu_upper < THRESHOLD_MU  # no warning from this alone


def test_evidence_rows_give_one_row_per_covered_cell_and_none_for_unknown():
    report = StationReport(**REPORT)
    rows = evidence_rows(report, 10)
    assert [r["cell"] for r in rows] == covered_cells(report.latitude_deg, report.longitude_deg, 10)
    assert all(r.keys() == {"station_id", "cell", "timestamp_ms", "mu", "mu_lower", "mu_upper"} for r in rows)
    assert {(r["station_id"], r["timestamp_ms"], r["mu"]) for r in rows} == {
        ("rws-a9-km12", REPORT["timestamp_ms"], 0.12)
    }
    assert evidence_rows(StationReport(**{**REPORT, "surface_state": "unknown"}), 10) == []


def test_a_stored_reports_evidence_reads_back_as_the_reports_own(storage):
    """What a cluster API replica hands on again for a duplicate: the evidence of the report as stored, the same rows
    as the report's own; none for a report without evidence; keys not stored are left out."""
    reports = parse(
        [
            REPORT,
            {**REPORT, "timestamp_ms": NOW_MS - 20_000, "surface_state": "dry"},
            {**REPORT, "timestamp_ms": NOW_MS - 10_000, "surface_state": "unknown"},
        ]
    )
    rows, evidence_of = stored_rows(reports, 10)
    assert storage.put_station_reports(rows) == set(evidence_of)
    stored = storage.station_reports_of([*reversed(evidence_of), ("rws-elsewhere", NOW_MS)])
    assert [(r["station_id"], r["timestamp_ms"]) for r in stored] == list(evidence_of)  # oldest first
    assert {(r["station_id"], r["timestamp_ms"]): stored_evidence_rows(r) for r in stored} == evidence_of
    assert [len(e) for e in evidence_of.values()] == [
        len(covered_cells(REPORT["latitude_deg"], REPORT["longitude_deg"], 10))
    ] * 2 + [0]
    assert storage.station_reports_of([]) == []
