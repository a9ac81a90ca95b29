"""Exports of the friction map and the warnings (DESIGN 3.6): GeoJSON, DATEX II v3, and the ETSI DENM shape.

Pure functions from CellSummary (roadgrip/cloud/domain/friction_map.py) and WarningEvent (roadgrip/cloud/domain/warnings.py)
to JSON-able dicts or XML text; no I/O.

GeoJSON (RFC 7946): one Polygon Feature per cell, the H3 boundary as a closed ring in [longitude, latitude] order, the
CellSummary fields as properties. A cell crossing the antimeridian is not split.

DENM: a JSON rendering of an ETSI EN 302 637-3 (v1.3.1) DENM, protocol version 2, field names and order as in its ASN.1
(DENM-PDU-Descriptions, ITS-Container v2): ENUMERATED values as their identifiers ("isCancellation", "lessThan100m"),
INTEGER values as numbers. Choices:
- actionID.sequenceNumber is the warning's own number (WarningEvent.action_sequence_number), the same in the new DENM,
  its updates and its cancellation: that is how receivers tie an update or a cancellation to the event. The count of
  updates (WarningEvent.sequence_number) is ours and goes in the "roadgrip" block.
- detectionTime is WarningEvent.evidence_ms: for a new DENM the detection; for an update the low-friction pass that
  refreshed it; for a cancellation the dry pass that ended it (or the expiry instant), as EN 302 637-3 asks ("for the
  DENM update, the time at which the event update is detected"). referenceTime is WarningEvent.updated_ms, when this
  DENM was generated. validityDuration counts from detectionTime, so the warning lapses at the same instant for a
  receiver as in the engine (last low pass + validity_s).
- TimestampIts: ITS time counts TAI milliseconds since 2004-01-01T00:00:00.000 UTC, so it runs ahead of Unix time by
  the leap seconds inserted since 2004: five, at the ends of 2005-12, 2008-12, 2012-06, 2015-06 and 2016-12 (IERS
  Bulletin C; none announced since, up to 2026). `timestamp_its_ms` adds each from the instant it took effect; a leap
  second announced later must be added to LEAP_SECONDS_UNIX_S.
- eventPosition: the cell centre in 0.1 microdegree (1e-7 degree) integers; the confidence ellipse is a circle of the
  cell's circumradius (the farthest boundary vertex from the centre) in centimetres, outOfRange (4094) when over 4093 cm
  as it is at resolution 10 (about 76 m); altitude unavailable.
- relevanceDistance: the smallest RelevanceDistance class that holds the cell's circumradius (lessThan100m at
  resolution 10).
- informationQuality (1..7; 0 would be "unavailable"): min(7, n_passes + 2 (n_vehicles - 1)). Independent vehicles count
  double because a vehicle's passes share its estimator's bias, tires and vehicle profile: two passes of one vehicle
  give 2, one pass each of two vehicles 4, three vehicles 7.
- eventType: causeCode 6 adverseWeatherCondition-Adhesion, subCauseCode 0 (unavailable): low mu does not tell ice
  from snow, oil or frost.
- stationType 15 (roadSideUnit): the cloud speaks through roadside units.
- A top-level "roadgrip" block (not part of the DENM) carries the cell, warning id, status, reason, the evidence
  (mu_upper, passes, vehicles) and the update count.

DATEX II v3: a d2:payload of xsi:type roa:MeasuredDataPublication with one roa:siteMeasurements per measured cell (status
"measured"; a cell without recent excited evidence has no friction to publish). Path to the value:
siteMeasurements / physicalQuantity[@index] / physicalQuantity[xsi:type SinglePhysicalQuantity] / basicData[xsi:type
RoadSurfaceConditionInformation] / roadSurfaceConditionMeasurements / com:friction / com:friction (a Float).
Checked against the v3 schema types as generated into Java (JAXB) in public repositories: PayloadPublication
(publicationTime, publicationCreator, attributes lang and modelBaseVersion="3"), InternationalIdentifier (country,
nationalIdentifier), MeasuredDataPublication (measurementSiteTableReference, headerInformation, siteMeasurements),
HeaderInformation (confidentiality, informationStatus), SiteMeasurements (measurementSiteReference, physicalQuantity,
measurementTimeDefault), PhysicalQuantity (pertinentLocation: a loc:LocationReference), SinglePhysicalQuantity
(basicData), BasicData (measurementOrCalculationTime), MeasurementOrCalculationTime (timeValue),
RoadSurfaceConditionInformation (roadSurfaceConditionMeasurements, typed in the common namespace),
RoadSurfaceConditionMeasurements (friction: com:FrictionValue), FrictionValue (friction: Float), DataValue (attribute
numberOfInputValuesUsed), PointByCoordinates / PointCoordinates (latitude, longitude); the physicalQuantity index
wrapper as in a real NDW v3 feed. Not verified, following the NOTES and v3 practice: loc:PointLocation directly holding
loc:pointByCoordinates, the enumeration values "noRestriction" and "real", the attributes of the versioned references,
and the country code: v3 types it as CountryCode, we write "other" (the v2 enumeration value) unless told a code.
The measurement site table referenced (one site per H3 cell) is virtual: we do not publish it, the location is in each
measurement's pertinentLocation. friction is written clipped to 0..1 (the coefficient road weather stations report; an
estimate above 1 on dry asphalt is written as 1).
"""

from __future__ import annotations

import bisect
import math
import xml.etree.ElementTree as ET
from collections.abc import Iterable
from dataclasses import asdict
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import h3

if TYPE_CHECKING:
    from roadgrip.cloud.domain.friction_map import CellSummary
    from roadgrip.cloud.domain.warnings import WarningEvent

ITS_EPOCH_UNIX_MS = 1_072_915_200_000  # 2004-01-01T00:00:00Z in Unix ms (UTC)
# Unix time (s) from which each leap second since 2004 counts: 2006-01-01, 2009-01-01, 2012-07-01, 2015-07-01, 2017-01-01
LEAP_SECONDS_UNIX_S = (1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800)

DENM_PROTOCOL_VERSION = 2
DENM_MESSAGE_ID = 1  # ItsPduHeader messageID denm(1)
CAUSE_ADVERSE_WEATHER_ADHESION = 6  # CauseCodeType adverseWeatherCondition-Adhesion
SUB_CAUSE_UNAVAILABLE = 0
STATION_TYPE_ROAD_SIDE_UNIT = 15
LATITUDE_UNAVAILABLE = 900_000_001
ALTITUDE_UNAVAILABLE = 800_001
SEMI_AXIS_OUT_OF_RANGE = 4094  # SemiAxisLength: cm, 4094 outOfRange
MAX_VALIDITY_S = 86_400  # ValidityDuration (0..86400)
# RelevanceDistance: (upper bound in m, identifier); beyond the last: over10km
RELEVANCE_DISTANCES = ((50.0, "lessThan50m"), (100.0, "lessThan100m"), (200.0, "lessThan200m"), (500.0, "lessThan500m"),
                       (1000.0, "lessThan1000m"), (5000.0, "lessThan5km"), (10000.0, "lessThan10km"))

NS = {
    "d2": "http://datex2.eu/schema/3/d2Payload",
    "com": "http://datex2.eu/schema/3/common",
    "roa": "http://datex2.eu/schema/3/roadTrafficData",
    "loc": "http://datex2.eu/schema/3/locationReferencing",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
}
for _prefix, _uri in NS.items():
    ET.register_namespace(_prefix, _uri)


def timestamp_its_ms(unix_ms: int) -> int:
    """ETSI TimestampIts: ms since 2004-01-01T00:00:00.000 UTC, counting the leap seconds since (TAI-like)."""
    unix_ms = int(unix_ms)
    if unix_ms < ITS_EPOCH_UNIX_MS:
        raise ValueError(f"unix_ms must be at or after 2004-01-01T00:00:00Z ({ITS_EPOCH_UNIX_MS}), got {unix_ms}")
    leap_seconds = bisect.bisect_right(LEAP_SECONDS_UNIX_S, unix_ms // 1000)
    return unix_ms - ITS_EPOCH_UNIX_MS + 1000 * leap_seconds


def iso_utc(unix_ms: int) -> str:
    """ISO 8601 UTC with milliseconds and a Z, e.g. 2026-01-15T08:00:00.000Z."""
    moment = datetime.fromtimestamp(int(unix_ms) / 1000.0, tz=UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


# ---------------------------------------------------------------------------------------------------------- GeoJSON

def geojson(cells: Iterable[CellSummary]) -> dict:
    """A GeoJSON FeatureCollection: one Polygon per cell (closed ring, [lon, lat]), the CellSummary as properties."""
    features = []
    for summary in cells:
        ring = [[lng, lat] for lat, lng in h3.cell_to_boundary(summary.cell)]
        ring.append(ring[0])
        features.append({"type": "Feature", "id": summary.cell,
                         "geometry": {"type": "Polygon", "coordinates": [ring]},
                         "properties": asdict(summary)})
    return {"type": "FeatureCollection", "features": features}


# ------------------------------------------------------------------------------------------------------------- DENM

def cell_radius_m(cell: str) -> float:
    """Circumradius of an H3 cell: the farthest boundary vertex from its centre, in metres."""
    centre = h3.cell_to_latlng(cell)
    return max(h3.great_circle_distance(centre, vertex, unit="m") for vertex in h3.cell_to_boundary(cell))


def relevance_distance(radius_m: float) -> str:
    for bound_m, name in RELEVANCE_DISTANCES:
        if radius_m < bound_m:
            return name
    return "over10km"


def information_quality(n_passes: int, n_vehicles: int) -> int:
    """InformationQuality 1..7 from the evidence: min(7, n_passes + 2 (n_vehicles - 1)), at least 1."""
    return max(1, min(7, n_passes + 2 * (max(n_vehicles, 1) - 1)))


def denm(event: WarningEvent, station_id: int | None = None) -> dict:
    """The DENM (EN 302 637-3, protocol version 2) of a warning event as JSON-able dict; see the module docstring.
    station_id defaults to the event's (the engine's) station."""
    station = event.station_id if station_id is None else int(station_id)
    radius_m = cell_radius_m(event.cell)
    semi_axis_cm = min(SEMI_AXIS_OUT_OF_RANGE, math.ceil(radius_m * 100.0))
    validity = math.ceil(event.validity_s)
    if not 0 <= validity <= MAX_VALIDITY_S:
        raise ValueError(f"validity_s must be within 0..{MAX_VALIDITY_S} s for a DENM, got {event.validity_s!r}")
    management = {
        "actionID": {"originatingStationID": station, "sequenceNumber": event.action_sequence_number},
        "detectionTime": timestamp_its_ms(event.evidence_ms),
        "referenceTime": timestamp_its_ms(event.updated_ms),
    }
    if event.status == "cancelled":
        management["termination"] = "isCancellation"
    management.update({
        "eventPosition": {
            "latitude": round(event.latitude_deg * 1e7),  # Latitude: 0.1 microdegree
            "longitude": round(event.longitude_deg * 1e7),
            "positionConfidenceEllipse": {"semiMajorConfidence": semi_axis_cm, "semiMinorConfidence": semi_axis_cm,
                                          "semiMajorOrientation": 0},  # a circle: orientation wgs84North
            "altitude": {"altitudeValue": ALTITUDE_UNAVAILABLE, "altitudeConfidence": "unavailable"},
        },
        "relevanceDistance": relevance_distance(radius_m),
        "relevanceTrafficDirection": "allTrafficDirections",
        "validityDuration": validity,
        "stationType": STATION_TYPE_ROAD_SIDE_UNIT,
    })
    return {
        "header": {"protocolVersion": DENM_PROTOCOL_VERSION, "messageID": DENM_MESSAGE_ID, "stationID": station},
        "denm": {
            "management": management,
            "situation": {
                "informationQuality": information_quality(event.n_passes, event.n_vehicles),
                "eventType": {"causeCode": CAUSE_ADVERSE_WEATHER_ADHESION, "subCauseCode": SUB_CAUSE_UNAVAILABLE},
            },
        },
        "roadgrip": {"cell": event.cell, "warning_id": event.warning_id, "status": event.status,
                     "reason": event.reason, "mu_upper": event.mu_upper, "n_passes": event.n_passes,
                     "n_vehicles": event.n_vehicles, "update": event.sequence_number},
    }


# -------------------------------------------------------------------------------------------------------- DATEX II

def _el(parent: ET.Element, prefix: str, name: str, text: str | None = None, **attrib: str) -> ET.Element:
    element = ET.SubElement(parent, f"{{{NS[prefix]}}}{name}", attrib)
    if text is not None:
        element.text = text
    return element


def _xsi_type(value: str) -> dict:
    return {f"{{{NS['xsi']}}}type": value}


def datex2_xml(cells: list[CellSummary], publication_time_ms: int, supplier: str = "roadgrip",
               country: str = "other") -> str:
    """DATEX II v3 MeasuredDataPublication of the measured cells' friction (see the module docstring), as XML text."""
    root = ET.Element(f"{{{NS['d2']}}}payload",
                      {**_xsi_type("roa:MeasuredDataPublication"), "lang": "en", "modelBaseVersion": "3"})
    _el(root, "com", "publicationTime", iso_utc(publication_time_ms))
    creator = _el(root, "com", "publicationCreator")
    _el(creator, "com", "country", country)
    _el(creator, "com", "nationalIdentifier", supplier)
    measured = [c for c in cells if c.status == "measured" and c.mu is not None]
    resolutions = sorted({h3.get_resolution(c.cell) for c in measured})
    table_id = f"{supplier}-h3-r{'-'.join(str(r) for r in resolutions) or 'none'}"
    _el(root, "roa", "measurementSiteTableReference", targetClass="roa:MeasurementSiteTable", id=table_id,
        version="1")
    header = _el(root, "roa", "headerInformation")
    _el(header, "com", "confidentiality", "noRestriction")
    _el(header, "com", "informationStatus", "real")
    for summary in measured:
        measured_at = iso_utc(summary.last_excited_ms if summary.last_excited_ms is not None else summary.last_ms)
        site = _el(root, "roa", "siteMeasurements")
        _el(site, "roa", "measurementSiteReference", targetClass="roa:MeasurementSite", id=summary.cell, version="1")
        index = _el(site, "roa", "physicalQuantity", index="1")
        quantity = _el(index, "roa", "physicalQuantity", **_xsi_type("roa:SinglePhysicalQuantity"))
        location = _el(quantity, "roa", "pertinentLocation", **_xsi_type("loc:PointLocation"))
        coordinates = _el(_el(location, "loc", "pointByCoordinates"), "loc", "pointCoordinates")
        _el(coordinates, "loc", "latitude", f"{summary.latitude_deg:.7f}")
        _el(coordinates, "loc", "longitude", f"{summary.longitude_deg:.7f}")
        basic = _el(quantity, "roa", "basicData", **_xsi_type("roa:RoadSurfaceConditionInformation"))
        _el(_el(basic, "roa", "measurementOrCalculationTime"), "roa", "timeValue", measured_at)
        surface = _el(basic, "roa", "roadSurfaceConditionMeasurements")
        friction = _el(surface, "com", "friction", numberOfInputValuesUsed=str(summary.n_excited))
        _el(friction, "com", "friction", f"{min(1.0, max(0.0, summary.mu)):.3f}")
        _el(_el(site, "roa", "measurementTimeDefault"), "roa", "timeValue", measured_at)
    return ET.tostring(root, encoding="unicode", xml_declaration=True)
