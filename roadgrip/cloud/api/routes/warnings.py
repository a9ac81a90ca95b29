"""Slippery-road warnings as DENMs (roadgrip/cloud/formats/denm.py), as stored."""

from fastapi import APIRouter

from roadgrip.cloud.api.deps import Backend, Caller, require

router = APIRouter()


@router.get("/v1/warnings")
def warnings(caller: Caller, backend: Backend, active: bool = True) -> dict:
    require(caller, "admin", "reader", "vehicle")
    rows = backend.storage.warnings(active_only=active)
    return {"warnings": [row["message"]["denm"] for row in rows]}
