"""Credentials the admin issues and revokes: readers, roadside stations (a vehicle's comes with its registration:
routes/vehicles.py); revocation of any but the admin's, at once."""

from typing import Annotated

from fastapi import APIRouter, HTTPException, Response
from fastapi import Path as PathParam
from pydantic import BaseModel, Field

from roadgrip.cloud.api.deps import Backend, Caller, require
from roadgrip.cloud.api.errors import errors
from roadgrip.data.telemetry import VEHICLE_ID_RE

router = APIRouter()


class ReaderRegistration(BaseModel):
    name: str = Field(pattern=VEHICLE_ID_RE.pattern)


class StationRegistration(BaseModel):
    station_id: str = Field(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-")


class Issued(BaseModel):
    name: str
    role: str
    secret: str = Field(description="shown once; stored only hashed")
    mqtt_url: str | None = None


@router.post("/v1/readers", status_code=201, response_model=Issued, responses=errors(400, 409, 422))
def register_reader(body: ReaderRegistration, caller: Caller, backend: Backend) -> Issued:
    require(caller, "admin")
    try:
        secret = backend.register_reader(body.name)
    except ValueError as exc:  # the name is taken
        raise HTTPException(409, str(exc)) from None
    return Issued(name=body.name, role="reader", secret=secret, mqtt_url=backend.mqtt_url)


@router.post("/v1/stations", status_code=201, response_model=Issued, responses=errors(400, 409, 422))
def register_station(body: StationRegistration, caller: Caller, backend: Backend) -> Issued:
    require(caller, "admin")
    try:
        secret = backend.register_station(body.station_id)
    except ValueError as exc:  # the name is taken
        raise HTTPException(409, str(exc)) from None
    return Issued(name=body.station_id, role="station", secret=secret, mqtt_url=backend.station_mqtt_url)


@router.delete("/v1/credentials/{name}", status_code=204, responses=errors(404, 409))
def revoke(
    name: Annotated[str, PathParam(pattern=VEHICLE_ID_RE.pattern)], caller: Caller, backend: Backend
) -> Response:
    require(caller, "admin")
    try:
        found = backend.revoke(name)
    except ValueError as exc:  # the admin's
        raise HTTPException(409, str(exc)) from None
    if not found:
        raise HTTPException(404, f"no active credential {name!r}")
    return Response(status_code=204)
