"""Slippery-road warnings as DENMs (roadgrip/cloud/formats/denm.py), as stored: JSON, or UPER-encoded and framed."""

from fastapi import APIRouter, Response

from roadgrip.cloud.api.deps import Backend, Caller, require
from roadgrip.cloud.formats.denm import denm_uper, frame

router = APIRouter()


@router.get("/v1/warnings")
def warnings(caller: Caller, backend: Backend, active: bool = True) -> dict:
    require(caller, "admin", "reader", "vehicle")
    rows = backend.storage.warnings(active_only=active)
    return {"warnings": [row["message"]["denm"] for row in rows]}


@router.get(
    "/v1/warnings/uper",
    response_class=Response,
    responses={
        200: {
            "content": {"application/octet-stream": {}},
            "description": "the DENMs of /v1/warnings UPER-encoded, each preceded by its length in bytes (4-byte "
            "unsigned big-endian)",
        }
    },
)
def warnings_uper(caller: Caller, backend: Backend, active: bool = True) -> Response:
    require(caller, "admin", "reader", "vehicle")
    rows = backend.storage.warnings(active_only=active)
    return Response(frame([denm_uper(row["message"]["denm"]) for row in rows]), media_type="application/octet-stream")
