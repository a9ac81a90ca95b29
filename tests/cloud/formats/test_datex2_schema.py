"""Every DATEX II document the service can publish (roadgrip/cloud/formats/datex2.py: the measured data, the measurement
site table, the GenericPublication of an empty map) validates against the official DATEX II v3 schema set
(tests/reference/datex2-v3.1/, DATEXII_3_D2Payload.xsd) with xmlschema: 0 errors. The validator rejects the two defects
a road operator's system found (country "other", a MeasuredDataPublication without siteMeasurements); every site the
data refers to is in the table; the country setting takes ISO 3166-1 alpha-2 codes only."""

import h3
import pytest
import xmlschema
from warning_route import PATCH, STEADY, T0_MS, drive

from roadgrip.cloud.domain.friction_map import FrictionMap
from roadgrip.cloud.formats.datex2 import check_country, datex2_site_table_xml, datex2_xml
from roadgrip.cloud.settings import Settings, load_settings

NS = {
    "d2": "http://datex2.eu/schema/3/d2Payload",
    "com": "http://datex2.eu/schema/3/common",
    "roa": "http://datex2.eu/schema/3/roadTrafficData",
    "loc": "http://datex2.eu/schema/3/locationReferencing",
}
XSI_TYPE = "{http://www.w3.org/2001/XMLSchema-instance}type"
DOCUMENTS = {"measured data": datex2_xml, "site table": datex2_site_table_xml}


def errors(schema: xmlschema.XMLSchema, text: str) -> list[str]:
    return [f"{e.path}: {e.reason}" for e in schema.iter_errors(text)]


def route_map() -> FrictionMap:
    """The test route driven once over its icy patch: measured cells, and a steadily driven one (mu unknown)."""
    fmap = FrictionMap()
    fmap.add(drive("a", T0_MS), T0_MS + 70_000)
    return fmap


def unexcited_map() -> FrictionMap:
    """Cells with evidence but none excited: no friction to publish anywhere."""
    fmap = FrictionMap()
    rows = [{**r, "excited": False, "mu_lower": 0.0, "mu_upper": 1.2} for r in drive("a", T0_MS)]
    fmap.add(rows, T0_MS + 70_000)
    return fmap


MAPS = {"route": route_map, "unexcited": unexcited_map, "empty": FrictionMap}


@pytest.mark.parametrize("document", DOCUMENTS)
@pytest.mark.parametrize("which", MAPS)
@pytest.mark.parametrize("country", ["NO", "de", "ZZ"])
def test_every_document_validates_against_the_official_schema(datex2_schema, document, which, country):
    cells = MAPS[which]().cells(T0_MS + 80_000)
    text = DOCUMENTS[document](cells, T0_MS + 80_000, country=country, resolution=10)
    assert errors(datex2_schema, text) == []
    decoded = datex2_schema.to_dict(text)
    assert decoded["com:publicationCreator"]["com:country"] == country.upper()
    expected = {
        "empty": "com:GenericPublication",
        "measured data": "roa:MeasuredDataPublication",
        "site table": "roa:MeasurementSiteTablePublication",
    }["empty" if which == "empty" else document]
    assert decoded["@xsi:type"] == expected


def test_the_route_map_has_cells_of_each_kind():
    statuses = {c.status for c in route_map().cells(T0_MS + 80_000)}
    assert "measured" in statuses and len(statuses) >= 2  # the schema test sees sites with and without friction
    assert {c.status for c in unexcited_map().cells(T0_MS + 80_000)} == {"no_recent_excited_evidence"}


def test_every_site_the_data_refers_to_is_in_the_table(datex2_schema):
    now_ms = T0_MS + 80_000
    cells = route_map().cells(now_ms)
    data = datex2_schema.to_dict(datex2_xml(cells, now_ms, country="NO", resolution=10))
    table = datex2_schema.to_dict(datex2_site_table_xml(cells, now_ms, country="NO", resolution=10))
    [reference] = data["roa:measurementSiteTableReference"]
    [site_table] = table["roa:measurementSiteTable"]
    assert (reference["@id"], reference["@version"]) == (site_table["@id"], site_table["@version"])
    sites = {s["@id"]: s for s in site_table["roa:measurementSite"]}
    referred = [m["roa:measurementSiteReference"] for m in data["roa:siteMeasurements"]]
    assert {(r["@id"], r["@version"]) for r in referred} == {(i, s["@version"]) for i, s in sites.items()}
    assert set(sites) == {c.cell for c in cells}
    for cell_id, site in sites.items():
        point = site["roa:measurementSiteLocation"]["loc:pointByCoordinates"]["loc:pointCoordinates"]
        assert h3.latlng_to_cell(point["loc:latitude"], point["loc:longitude"], 10) == cell_id
    with_friction = [m for m in data["roa:siteMeasurements"] if "roa:physicalQuantity" in m]
    assert {m["roa:measurementSiteReference"]["@id"] for m in with_friction} >= PATCH
    assert STEADY not in {m["roa:measurementSiteReference"]["@id"] for m in with_friction}  # not excited: no number
    # another set of cells is another table version
    fewer = FrictionMap()
    fewer.add(drive("a", T0_MS)[:300], T0_MS + 70_000)
    versions = {
        datex2_schema.to_dict(datex2_site_table_xml(m.cells(now_ms), now_ms, country="NO", resolution=10))[
            "roa:measurementSiteTable"
        ][0]["@version"]
        for m in (route_map(), fewer)
    }
    assert len(versions) == 2


def test_the_validator_rejects_what_a_road_operators_system_rejected(datex2_schema):
    cells = route_map().cells(T0_MS + 80_000)
    text = datex2_xml(cells, T0_MS + 80_000, country="NO", resolution=10)
    other = text.replace("<com:country>NO</com:country>", "<com:country>other</com:country>")
    assert other != text and any("country" in e for e in errors(datex2_schema, other))
    start, end = text.index("<roa:siteMeasurements>"), text.rindex("</roa:siteMeasurements>")
    without_sites = text[:start] + text[end + len("</roa:siteMeasurements>") :]
    assert any("siteMeasurements" in e for e in errors(datex2_schema, without_sites))


def test_the_country_is_an_iso_3166_alpha_2_code(monkeypatch):
    assert Settings().datex2_country == "ZZ"  # the default claims no country
    assert load_settings(datex2_country="no").datex2_country == "NO"
    assert check_country("DE") == "DE"
    for bad in ("other", "NOR", "N0", "", "n"):
        with pytest.raises(ValueError) as error:
            load_settings(datex2_country=bad)
        message = str(error.value)
        assert "\n" not in message and "datex2_country" in message and "ISO 3166-1 alpha-2" in message, message
        with pytest.raises(ValueError, match="ISO 3166-1 alpha-2"):
            datex2_xml([], T0_MS, country=bad, resolution=10)
    monkeypatch.setenv("ROADGRIP_DATEX2_COUNTRY", "se")
    assert load_settings().datex2_country == "SE"
