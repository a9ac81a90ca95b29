"""Exports: DATEX II v3 parses back with a site per cell and one friction per measured cell (the schema itself:
test_datex2_schema.py), GeoJSON has one home, TimestampIts counts the
leap seconds, the DENM's enumerations and quality."""

import calendar
import json
import xml.etree.ElementTree as ET

import h3
import pytest

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.domain.warnings import WarningEvent
from roadgrip.cloud.formats.datex2 import datex2_xml
from roadgrip.cloud.formats.denm import cell_radius_m, denm, information_quality, relevance_distance, timestamp_its_ms
from roadgrip.cloud.formats.geojson import geojson

T0_MS = calendar.timegm((2026, 1, 15, 8, 0, 0)) * 1000
NS = {
    "d2": "http://datex2.eu/schema/3/d2Payload",
    "com": "http://datex2.eu/schema/3/common",
    "roa": "http://datex2.eu/schema/3/roadTrafficData",
    "loc": "http://datex2.eu/schema/3/locationReferencing",
}
XSI_TYPE = "{http://www.w3.org/2001/XMLSchema-instance}type"


def est(lat, lon, mu, excited=True, t_ms=T0_MS, vehicle="v1"):
    return {
        "vehicle_id": vehicle,
        "timestamp_ms": t_ms,
        "latitude_deg": lat,
        "longitude_deg": lon,
        "mu": mu,
        "mu_lower": mu - 0.1,
        "mu_upper": mu + 0.1,
        "excited": excited,
    }


def sample_map() -> FrictionMap:
    fmap = FrictionMap()
    fmap.add(
        [
            est(38.0, 114.5, 0.25),
            est(38.0, 114.5, 0.35, vehicle="v2"),  # measured, mu 0.3
            est(38.01, 114.51, 0.7, vehicle="v3"),  # measured, mu 0.7
            est(38.02, 114.52, 0.5, excited=False, vehicle="v4"),
        ]
    )  # no recent excited evidence: not published
    # (one vehicle per place: of one vehicle seen in three cells at one instant, the third row would be too late,
    # roadgrip/cloud/domain/passes.py)
    return fmap


def unix_ms(*ymdhms) -> int:
    return calendar.timegm(ymdhms) * 1000


# ---------------------------------------------------------------------------------------------------------- DATEX II


def test_datex2_parses_with_a_site_per_cell_and_one_friction_per_measured_cell():
    cells = sample_map().cells(T0_MS)
    measured = {c.cell: c for c in cells if c.status == "measured"}
    assert len(cells) == 3 and len(measured) == 2
    text = datex2_xml(cells, T0_MS + 1000, country="NO", resolution=10, supplier="roadgrip-test")
    root = ET.fromstring(text)
    assert root.tag == f"{{{NS['d2']}}}payload" and root.get(XSI_TYPE) == "roa:MeasuredDataPublication"
    assert root.get("modelBaseVersion") == "3"
    assert root.findtext("com:publicationTime", namespaces=NS) == "2026-01-15T08:00:01.000Z"
    assert root.findtext("com:publicationCreator/com:country", namespaces=NS) == "NO"
    assert root.findtext("com:publicationCreator/com:nationalIdentifier", namespaces=NS) == "roadgrip-test"
    sites = root.findall("roa:siteMeasurements", NS)
    assert [s.find("roa:measurementSiteReference", NS).get("id") for s in sites] == [c.cell for c in cells]
    for site in sites:
        cell_id = site.find("roa:measurementSiteReference", NS).get("id")
        if cell_id not in measured:  # mu unknown: the site without a quantity, no number
            assert site.find("roa:physicalQuantity", NS) is None
            continue
        cell = measured[cell_id]
        quantity = site.find("roa:physicalQuantity/roa:physicalQuantity", NS)
        assert quantity.get(XSI_TYPE) == "roa:SinglePhysicalQuantity"
        basic = quantity.find("roa:basicData", NS)
        assert basic.get(XSI_TYPE) == "roa:RoadSurfaceConditionInformation"
        frictions = basic.findall("roa:roadSurfaceConditionMeasurements/com:friction/com:friction", NS)
        assert len(frictions) == 1 and float(frictions[0].text) == pytest.approx(cell.mu, abs=5e-4)
        point = quantity.find("roa:pertinentLocation/loc:pointByCoordinates/loc:pointCoordinates", NS)
        lat, lon = (
            float(point.findtext("loc:latitude", namespaces=NS)),
            float(point.findtext("loc:longitude", namespaces=NS)),
        )
        assert h3.latlng_to_cell(lat, lon, 10) == cell.cell
        assert (
            basic.findtext("roa:measurementOrCalculationTime/roa:timeValue", namespaces=NS)
            == "2026-01-15T08:00:00.000Z"
        )
    assert sorted(float(f.text) for f in root.iterfind(".//com:friction/com:friction", NS)) == pytest.approx(
        sorted(c.mu for c in measured.values()), abs=5e-4
    )


def test_datex2_of_an_empty_map_is_a_generic_publication():
    root = ET.fromstring(datex2_xml([], T0_MS, country="NO", resolution=10))
    assert root.get(XSI_TYPE) == "com:GenericPublication"
    assert root.findtext("com:genericPublicationName", namespaces=NS) == "MeasuredDataPublication"
    assert root.findall("roa:siteMeasurements", NS) == []


def test_datex2_clips_friction_to_the_unit_interval():
    fmap = FrictionMap()
    fmap.add([est(38.0, 114.5, 1.3, vehicle=f"v{k}") for k in range(4)])  # four passes: mu >= 1.2, median above 1
    assert fmap.cells(T0_MS)[0].mu > 1.0
    root = ET.fromstring(datex2_xml(fmap.cells(T0_MS), T0_MS, country="NO", resolution=10))
    assert float(root.find(".//com:friction/com:friction", NS).text) == 1.0


# ----------------------------------------------------------------------------------------------------------- GeoJSON


def test_geojson_has_one_home():
    fmap = sample_map()
    assert not hasattr(fmap, "to_geojson")  # the domain renders no format: formats/geojson.py does
    json.dumps(geojson(fmap.cells(T0_MS)))  # plain JSON


# ------------------------------------------------------------------------------------------------------ TimestampIts


def test_timestamp_its_counts_from_2004_with_the_leap_seconds_since():
    assert timestamp_its_ms(unix_ms(2004, 1, 1, 0, 0, 0)) == 0
    assert timestamp_its_ms(unix_ms(2004, 1, 1, 0, 0, 0) + 1) == 1
    day_ms = 86_400_000
    assert timestamp_its_ms(unix_ms(2005, 12, 31, 23, 59, 59)) == (731 * day_ms - 1000)  # 2004 is a leap year
    assert timestamp_its_ms(unix_ms(2006, 1, 1, 0, 0, 0)) == 731 * day_ms + 1000  # the 2005-12-31 leap second
    # TAI - UTC was 32 s in 2004 and is 37 s since 2017-01-01 (IERS Bulletin C): five more
    for moment in [(2017, 1, 1, 0, 0, 0), (2026, 1, 15, 8, 0, 0)]:
        assert timestamp_its_ms(unix_ms(*moment)) == unix_ms(*moment) - unix_ms(2004, 1, 1, 0, 0, 0) + 5000
    assert (
        timestamp_its_ms(unix_ms(2016, 12, 31, 23, 59, 59))
        == unix_ms(2016, 12, 31, 23, 59, 59) - unix_ms(2004, 1, 1, 0, 0, 0) + 4000
    )
    with pytest.raises(ValueError, match="2004"):
        timestamp_its_ms(unix_ms(2003, 12, 31, 23, 59, 59))


# --------------------------------------------------------------------------------------------------------------- DENM


def event(status="active", reason="low friction", cell=None, n_passes=2, n_vehicles=2) -> WarningEvent:
    cell = cell or h3.latlng_to_cell(38.0, 114.5, 10)
    lat, lon = h3.cell_to_latlng(cell)
    return WarningEvent(
        warning_id=f"{cell}-{T0_MS}",
        cell=cell,
        status=status,
        reason=reason,
        detection_ms=T0_MS,
        updated_ms=T0_MS + 500,
        latitude_deg=lat,
        longitude_deg=lon,
        mu_upper=0.3,
        n_passes=n_passes,
        n_vehicles=n_vehicles,
        sequence_number=0,
        validity_s=600.0,
        evidence_ms=T0_MS,
        action_sequence_number=17,
        station_id=9,
    )


def test_denm_fields_and_termination():
    active = denm(event())
    json.dumps(active)
    management = active["denm"]["management"]
    assert list(management) == [
        "actionID",
        "detectionTime",
        "referenceTime",
        "eventPosition",
        "relevanceDistance",
        "relevanceTrafficDirection",
        "validityDuration",
        "stationType",
    ]  # ASN.1 order
    assert management["actionID"] == {"originatingStationID": 9, "sequenceNumber": 17}
    assert management["referenceTime"] - management["detectionTime"] == 500
    assert management["relevanceTrafficDirection"] == "allTrafficDirections"
    ellipse = management["eventPosition"]["positionConfidenceEllipse"]
    assert ellipse["semiMajorConfidence"] == ellipse["semiMinorConfidence"] == 4094  # a 76 m cell: outOfRange
    assert management["eventPosition"]["altitude"] == {"altitudeValue": 800001, "altitudeConfidence": "unavailable"}
    cancelled = denm(event(status="cancelled", reason="recovered"))
    assert cancelled["denm"]["management"]["termination"] == "isCancellation"
    assert cancelled["roadgrip"]["reason"] == "recovered"
    assert denm(event(), station_id=3)["header"]["stationID"] == 3


def test_denm_position_confidence_fits_a_small_cell():
    cell = h3.latlng_to_cell(38.0, 114.5, 12)  # edge about 11 m
    ellipse = denm(event(cell=cell))["denm"]["management"]["eventPosition"]["positionConfidenceEllipse"]
    radius_cm = cell_radius_m(cell) * 100
    assert radius_cm <= ellipse["semiMajorConfidence"] < radius_cm + 1
    assert denm(event(cell=cell))["denm"]["management"]["relevanceDistance"] == "lessThan50m"


@pytest.mark.parametrize(
    ("radius_m", "name"),
    [
        (30, "lessThan50m"),
        (76, "lessThan100m"),
        (150, "lessThan200m"),
        (400, "lessThan500m"),
        (900, "lessThan1000m"),
        (4000, "lessThan5km"),
        (9000, "lessThan10km"),
        (20000, "over10km"),
    ],
)
def test_relevance_distance_classes(radius_m, name):
    assert relevance_distance(radius_m) == name


@pytest.mark.parametrize(
    ("n_passes", "n_vehicles", "quality"),
    [(1, 1, 1), (2, 1, 2), (2, 2, 4), (3, 3, 7), (4, 2, 6), (20, 1, 7), (0, 0, 1)],
)
def test_information_quality(n_passes, n_vehicles, quality):
    assert information_quality(n_passes, n_vehicles) == quality
