"""The friction map: GeoJSON (roadgrip/cloud/formats/geojson.py) and DATEX II v3 (roadgrip/cloud/formats/datex2.py:
the measured data and the measurement site table it refers to), read at the backend's clock."""

from fastapi import APIRouter, Response

from roadgrip.cloud.api.deps import Backend, Caller, require
from roadgrip.cloud.formats.datex2 import datex2_site_table_xml, datex2_xml
from roadgrip.cloud.formats.geojson import geojson

router = APIRouter()


@router.get("/v1/map")
def friction_map(caller: Caller, backend: Backend) -> dict:
    require(caller, "admin", "reader")
    fmap, now_ms = backend.current_map()
    return geojson(fmap.cells(now_ms))


def _datex2(backend, render) -> Response:
    fmap, now_ms = backend.current_map()
    text = render(fmap.cells(now_ms), now_ms, country=backend.settings.datex2_country, resolution=fmap.resolution)
    return Response(text, media_type="application/xml")


@router.get(
    "/v1/map/datex2",
    response_class=Response,
    responses={200: {"content": {"application/xml": {}}, "description": "DATEX II v3 MeasuredDataPublication"}},
)
def datex2(caller: Caller, backend: Backend) -> Response:
    require(caller, "admin", "reader")
    return _datex2(backend, datex2_xml)


@router.get(
    "/v1/map/datex2/sites",
    response_class=Response,
    responses={200: {"content": {"application/xml": {}}, "description": "DATEX II v3 MeasurementSiteTablePublication"}},
)
def datex2_sites(caller: Caller, backend: Backend) -> Response:
    require(caller, "admin", "reader")
    return _datex2(backend, datex2_site_table_xml)
