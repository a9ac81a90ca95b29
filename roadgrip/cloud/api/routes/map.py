"""The friction map: GeoJSON (roadgrip/cloud/formats/geojson.py) and DATEX II v3 (roadgrip/cloud/formats/datex2.py),
read at the backend's clock."""

from fastapi import APIRouter, Response

from roadgrip.cloud.api.deps import Backend, Caller, require
from roadgrip.cloud.formats.datex2 import datex2_xml
from roadgrip.cloud.formats.geojson import geojson

router = APIRouter()


@router.get("/v1/map")
def friction_map(caller: Caller, backend: Backend) -> dict:
    require(caller, "admin", "reader")
    fmap, now_ms = backend.current_map()
    return geojson(fmap.cells(now_ms))


@router.get(
    "/v1/map/datex2",
    response_class=Response,
    responses={200: {"content": {"application/xml": {}}, "description": "DATEX II v3 publication"}},
)
def datex2(caller: Caller, backend: Backend) -> Response:
    require(caller, "admin", "reader")
    fmap, now_ms = backend.current_map()
    return Response(datex2_xml(fmap.cells(now_ms), now_ms), media_type="application/xml")
