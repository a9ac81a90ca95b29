"""The friction map (CellSummary, roadgrip/cloud/domain/friction_map.py) as a DATEX II v3 document. A pure function;
no I/O.

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

import xml.etree.ElementTree as ET
from datetime import UTC, datetime
from typing import TYPE_CHECKING

import h3

if TYPE_CHECKING:
    from roadgrip.cloud.domain.friction_map import CellSummary

NS = {
    "d2": "http://datex2.eu/schema/3/d2Payload",
    "com": "http://datex2.eu/schema/3/common",
    "roa": "http://datex2.eu/schema/3/roadTrafficData",
    "loc": "http://datex2.eu/schema/3/locationReferencing",
    "xsi": "http://www.w3.org/2001/XMLSchema-instance",
}
for _prefix, _uri in NS.items():
    ET.register_namespace(_prefix, _uri)


def iso_utc(unix_ms: int) -> str:
    """ISO 8601 UTC with milliseconds and a Z, e.g. 2026-01-15T08:00:00.000Z."""
    moment = datetime.fromtimestamp(int(unix_ms) / 1000.0, tz=UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def _el(parent: ET.Element, prefix: str, name: str, text: str | None = None, **attrib: str) -> ET.Element:
    element = ET.SubElement(parent, f"{{{NS[prefix]}}}{name}", attrib)
    if text is not None:
        element.text = text
    return element


def _xsi_type(value: str) -> dict:
    return {f"{{{NS['xsi']}}}type": value}


def datex2_xml(
    cells: list[CellSummary], publication_time_ms: int, supplier: str = "roadgrip", country: str = "other"
) -> str:
    """DATEX II v3 MeasuredDataPublication of the measured cells' friction (see the module docstring), as XML text."""
    root = ET.Element(
        f"{{{NS['d2']}}}payload", {**_xsi_type("roa:MeasuredDataPublication"), "lang": "en", "modelBaseVersion": "3"}
    )
    _el(root, "com", "publicationTime", iso_utc(publication_time_ms))
    creator = _el(root, "com", "publicationCreator")
    _el(creator, "com", "country", country)
    _el(creator, "com", "nationalIdentifier", supplier)
    measured = [c for c in cells if c.status == "measured" and c.mu is not None]
    resolutions = sorted({h3.get_resolution(c.cell) for c in measured})
    table_id = f"{supplier}-h3-r{'-'.join(str(r) for r in resolutions) or 'none'}"
    _el(root, "roa", "measurementSiteTableReference", targetClass="roa:MeasurementSiteTable", id=table_id, version="1")
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
