"""The friction map (CellSummary, roadgrip/cloud/domain/friction_map.py) as DATEX II v3 documents: the measured data
(`datex2_xml`) and the measurement site table it refers to (`datex2_site_table_xml`). Pure functions; no I/O.

Every document validates against the official DATEX II v3 schema set (DATEXII_3_D2Payload.xsd, "version 3.1"; a copy in
tests/reference/datex2-v3.1/, where tests/cloud/formats/test_datex2_schema.py validates every kind of document with
xmlschema). Its root is the only global element, d2:payload (a com:PayloadPublication, abstract: xsi:type names the
publication), with publicationTime and publicationCreator (com:InternationalIdentifier: country, a com:CountryCode of at
most two characters, here an ISO 3166-1 alpha-2 code, `check_country`; nationalIdentifier, the supplier).

Sites: one measurement site per H3 cell of the map (resolution `resolution`, the map's). A site's id is the cell id,
its location the cell centre (loc:PointLocation / pointByCoordinates), its version "1" (a cell never moves); its one
measurement characteristic (index 1) is roadSurfaceConditionInformation. The table holds the sites of the cells the map
holds now (evidence younger than map_max_age_s): id `{supplier}-h3-r{resolution}`, version the first 16 hex digits of
the SHA-256 of its sorted cell ids (`site_table_version`), so the version changes exactly when a cell enters or leaves
the map and a consumer that meets a version it does not hold fetches the table again.

Measured data (roa:MeasuredDataPublication): the table's reference (the same id and version as the table of the same
cells), headerInformation (noRestriction, real), and one roa:siteMeasurements per cell of the map: a measured cell
(recent excited evidence) carries its friction, path siteMeasurements / physicalQuantity[@index 1] / physicalQuantity
[xsi:type SinglePhysicalQuantity] / basicData[xsi:type RoadSurfaceConditionInformation] /
roadSurfaceConditionMeasurements / com:friction / com:friction (a Float, clipped to 0..1: the coefficient road weather
stations report; an estimate above 1 on dry asphalt is written as 1), with numberOfInputValuesUsed its excited
estimates and its time the newest excited evidence. Any other cell ("bounded", "no_recent_excited_evidence": mu not
known) is a siteMeasurements without physicalQuantity (the schema's minOccurs 0): the site is known, its friction is
not, and no number is published for it. measurementTimeDefault: the newest excited evidence, else the newest evidence.

An empty map (no cell at all) has no site: the schema requires at least one siteMeasurements in a MeasuredDataPublication
and at least one measurementSite in a table, so both routes answer a com:GenericPublication instead, the schema's
publication without content (genericPublicationName MeasuredDataPublication or MeasurementSiteTablePublication, a
feedDescription saying the map holds no cell).
"""

from __future__ import annotations

import hashlib
import re
import xml.etree.ElementTree as ET
from datetime import UTC, datetime
from typing import TYPE_CHECKING

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

MEASURED = "measured"  # the CellSummary status whose friction is published
COUNTRY_RE = re.compile(r"[A-Z]{2}")
FRICTION_INDEX = "1"  # the physicalQuantity index of the friction, and the site's characteristic of that index
EMPTY_MAP = "the friction map holds no cell yet: no measurement site, no measurement"


def check_country(code: str) -> str:
    """An ISO 3166-1 alpha-2 country code (two letters; lower case is taken as upper case), as com:CountryCode takes
    it. The format is checked, not the list of assigned codes."""
    if not isinstance(code, str) or COUNTRY_RE.fullmatch(code.upper()) is None:
        raise ValueError(f"country must be an ISO 3166-1 alpha-2 code (two letters, e.g. NO, DE, CN), got {code!r}")
    return code.upper()


def iso_utc(unix_ms: int) -> str:
    """ISO 8601 UTC with milliseconds and a Z, e.g. 2026-01-15T08:00:00.000Z."""
    moment = datetime.fromtimestamp(int(unix_ms) / 1000.0, tz=UTC)
    return moment.isoformat(timespec="milliseconds").replace("+00:00", "Z")


def site_table_id(supplier: str, resolution: int) -> str:
    return f"{supplier}-h3-r{int(resolution)}"


def site_table_version(cells: list[CellSummary]) -> str:
    """The table's version: names its set of sites (the first 16 hex digits of the SHA-256 of the sorted cell ids)."""
    return hashlib.sha256(",".join(sorted(c.cell for c in cells)).encode()).hexdigest()[:16]


def _el(parent: ET.Element, prefix: str, name: str, text: str | None = None, **attrib: str) -> ET.Element:
    element = ET.SubElement(parent, f"{{{NS[prefix]}}}{name}", attrib)
    if text is not None:
        element.text = text
    return element


def _xsi_type(value: str) -> dict:
    return {f"{{{NS['xsi']}}}type": value}


def _payload(
    publication: str, publication_time_ms: int, country: str, supplier: str, description: str | None = None
) -> ET.Element:
    """A d2:payload of xsi:type `publication` with its (feedDescription,) publicationTime and publicationCreator."""
    root = ET.Element(f"{{{NS['d2']}}}payload", {**_xsi_type(publication), "lang": "en", "modelBaseVersion": "3"})
    if description is not None:
        _el(_el(_el(root, "com", "feedDescription"), "com", "values"), "com", "value", description, lang="en")
    _el(root, "com", "publicationTime", iso_utc(publication_time_ms))
    creator = _el(root, "com", "publicationCreator")
    _el(creator, "com", "country", check_country(country))
    _el(creator, "com", "nationalIdentifier", supplier)
    return root


def _generic(name: str, publication_time_ms: int, country: str, supplier: str) -> str:
    """The com:GenericPublication of an empty map (module docstring)."""
    root = _payload("com:GenericPublication", publication_time_ms, country, supplier, EMPTY_MAP)
    _el(root, "com", "genericPublicationName", name)
    return _text(root)


def _header(root: ET.Element) -> None:
    header = _el(root, "roa", "headerInformation")
    _el(header, "com", "confidentiality", "noRestriction")
    _el(header, "com", "informationStatus", "real")


def _point(parent: ET.Element, name: str, summary: CellSummary) -> None:
    location = _el(parent, "roa", name, **_xsi_type("loc:PointLocation"))
    coordinates = _el(_el(location, "loc", "pointByCoordinates"), "loc", "pointCoordinates")
    _el(coordinates, "loc", "latitude", f"{summary.latitude_deg:.7f}")
    _el(coordinates, "loc", "longitude", f"{summary.longitude_deg:.7f}")


def _text(root: ET.Element) -> str:
    return ET.tostring(root, encoding="unicode", xml_declaration=True)


def datex2_xml(
    cells: list[CellSummary], publication_time_ms: int, country: str, resolution: int, supplier: str = "roadgrip"
) -> str:
    """DATEX II v3 MeasuredDataPublication of the map's cells (the module docstring), as XML text; a
    GenericPublication when there is no cell."""
    if not cells:
        return _generic("MeasuredDataPublication", publication_time_ms, country, supplier)
    root = _payload("roa:MeasuredDataPublication", publication_time_ms, country, supplier)
    _el(
        root,
        "roa",
        "measurementSiteTableReference",
        targetClass="roa:MeasurementSiteTable",
        id=site_table_id(supplier, resolution),
        version=site_table_version(cells),
    )
    _header(root)
    for summary in cells:
        measured = summary.status == MEASURED and summary.mu is not None
        newest_ms = summary.last_excited_ms if summary.last_excited_ms is not None else summary.last_ms
        site = _el(root, "roa", "siteMeasurements")
        _el(site, "roa", "measurementSiteReference", targetClass="roa:MeasurementSite", id=summary.cell, version="1")
        if measured:
            index = _el(site, "roa", "physicalQuantity", index=FRICTION_INDEX)
            quantity = _el(index, "roa", "physicalQuantity", **_xsi_type("roa:SinglePhysicalQuantity"))
            _point(quantity, "pertinentLocation", summary)
            basic = _el(quantity, "roa", "basicData", **_xsi_type("roa:RoadSurfaceConditionInformation"))
            _el(_el(basic, "roa", "measurementOrCalculationTime"), "roa", "timeValue", iso_utc(newest_ms))
            surface = _el(basic, "roa", "roadSurfaceConditionMeasurements")
            friction = _el(surface, "com", "friction", numberOfInputValuesUsed=str(summary.n_excited))
            _el(friction, "com", "friction", f"{min(1.0, max(0.0, summary.mu)):.3f}")
        _el(_el(site, "roa", "measurementTimeDefault"), "roa", "timeValue", iso_utc(newest_ms))
    return _text(root)


def datex2_site_table_xml(
    cells: list[CellSummary], publication_time_ms: int, country: str, resolution: int, supplier: str = "roadgrip"
) -> str:
    """DATEX II v3 MeasurementSiteTablePublication: one site per cell of the map (module docstring), as XML text; a
    GenericPublication when there is no cell."""
    if not cells:
        return _generic("MeasurementSiteTablePublication", publication_time_ms, country, supplier)
    root = _payload("roa:MeasurementSiteTablePublication", publication_time_ms, country, supplier)
    _header(root)
    table = _el(
        root,
        "roa",
        "measurementSiteTable",
        id=site_table_id(supplier, resolution),
        version=site_table_version(cells),
    )
    _el(table, "roa", "measurementSiteTableIdentification", f"H3 cells at resolution {int(resolution)}")
    for summary in cells:
        site = _el(table, "roa", "measurementSite", id=summary.cell, version="1")
        _el(site, "roa", "measurementSiteIdentification", summary.cell)
        index = _el(site, "roa", "measurementSpecificCharacteristics", index=FRICTION_INDEX)
        characteristics = _el(index, "roa", "measurementSpecificCharacteristics")
        _el(characteristics, "roa", "specificMeasurementValueType", "roadSurfaceConditionInformation")
        _point(site, "measurementSiteLocation", summary)
    return _text(root)
