"""Vehicles: registration with a profile (CONTRACTS 3.2), a vehicle's profile, its estimates (CONTRACTS 3.4) over a time
range."""

from typing import Annotated

from fastapi import APIRouter, HTTPException, Query
from pydantic import AfterValidator, BaseModel, Field, PrivateAttr

from roadgrip.cloud.api.backend import VehicleIdRefused
from roadgrip.cloud.api.deps import Backend, Caller, QueryInt, VehicleId, may_read_vehicle, require
from roadgrip.cloud.api.errors import Refused, errors
from roadgrip.cloud.api.routes.credentials import Issued
from roadgrip.data.telemetry import VEHICLE_ID_RE
from roadgrip.vehicle.params import VEHICLES, VehicleParams, vehicle_by_name

RESERVED_IDS = ("latest",)  # path segments of /v1/vehicles/... that are not vehicles
MAX_MS = 2**63 - 1  # times are BIGINT columns: a larger bound would overflow the database driver (found by fuzzing)

router = APIRouter()


class VehicleRegistration(BaseModel):
    vehicle_id: str = Field(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-, not 'latest'")
    profile: str | dict = Field(
        "paper-suv",
        description=f"a known vehicle ({', '.join(VEHICLES)}) or a profile mapping with the CONTRACTS 3.2 fields (SI)",
    )
    _params: VehicleParams | None = PrivateAttr(None)  # the profile read, by `_checked`

    @property
    def params(self) -> VehicleParams:
        return self._params


def _checked(body: VehicleRegistration | list[VehicleRegistration]):
    """The rules of a registration beyond its schema, for one vehicle or a list (Refused, naming where, for the first
    broken): no reserved vehicle_id; a profile that is a known vehicle or valid CONTRACTS 3.2 fields, with no text a
    database cannot store. Each registration gets its profile read (`params`)."""
    batch = body if isinstance(body, list) else [body]
    reserved = [item.vehicle_id for item in batch if item.vehicle_id in RESERVED_IDS]
    if reserved:
        raise Refused(f"vehicle_id {reserved[0]!r} is reserved (a route of the API)")
    for k, item in enumerate(batch):
        where = "profile" if not isinstance(body, list) else f"[{k}].profile"
        try:
            params = (
                vehicle_by_name(item.profile)
                if isinstance(item.profile, str)
                else VehicleParams.from_dict(item.profile)
            )
        except (ValueError, TypeError, KeyError) as exc:
            raise Refused(f"{where}: {exc}") from None
        unstorable = _unstorable_text(params.to_dict(), where)
        if unstorable is not None:
            raise Refused(f"{unstorable}: text with a NUL character or a lone surrogate cannot be stored")
        item._params = params
    return body


Registration = Annotated[VehicleRegistration | list[VehicleRegistration], AfterValidator(_checked)]


def _unstorable_text(value, where: str) -> str | None:
    """Where in a JSON-like value a string holds what PostgreSQL cannot store (a NUL character; a lone UTF-16
    surrogate, which JSON's \\u escapes can carry), or None."""
    if isinstance(value, str):
        return where if "\x00" in value or any("\ud800" <= c <= "\udfff" for c in value) else None
    items = value.items() if isinstance(value, dict) else enumerate(value) if isinstance(value, list) else ()
    for key, item in items:
        found = _unstorable_text(key, f"{where} (a key)") or _unstorable_text(item, f"{where}.{key}")
        if found is not None:
            return found
    return None


@router.post("/v1/vehicles", status_code=201, response_model=Issued | list[Issued], responses=errors(400, 409, 422))
def register_vehicles(body: Registration, caller: Caller, backend: Backend):
    """One vehicle, or a list (a fleet at once: one broker reload); all or nothing."""
    require(caller, "admin")
    batch = body if isinstance(body, list) else [body]
    try:
        secrets = backend.register_vehicles([(item.vehicle_id, item.params) for item in batch])
    except VehicleIdRefused:
        raise  # 422 (roadgrip/cloud/api/errors.py)
    except ValueError as exc:  # a vehicle_id taken, or given twice
        raise HTTPException(409, str(exc)) from None
    answers = [
        Issued(name=item.vehicle_id, role="vehicle", secret=secret, mqtt_url=backend.mqtt_url)
        for item, secret in zip(batch, secrets)
    ]
    return answers if isinstance(body, list) else answers[0]


@router.get("/v1/vehicles/{vehicle_id}", responses=errors(404))
def vehicle_profile(vehicle_id: VehicleId, caller: Caller, backend: Backend) -> dict:
    may_read_vehicle(caller, vehicle_id)
    profile = backend.storage.vehicle_profile(vehicle_id)
    if profile is None:
        raise HTTPException(404, f"no vehicle {vehicle_id!r}")
    return {"vehicle_id": vehicle_id, "profile": profile}


@router.get("/v1/vehicles/{vehicle_id}/estimates")
def estimates(
    vehicle_id: VehicleId,
    caller: Caller,
    backend: Backend,
    start_ms: Annotated[
        int | None, QueryInt, Query(ge=0, le=MAX_MS, description="from (ms since epoch, inclusive)")
    ] = None,
    end_ms: Annotated[
        int | None, QueryInt, Query(ge=0, le=MAX_MS, description="to (ms since epoch, exclusive)")
    ] = None,
    limit: Annotated[int, QueryInt, Query(ge=1, le=100_000)] = 10_000,
) -> dict:
    may_read_vehicle(caller, vehicle_id)
    rows = backend.storage.estimates(vehicle_id, start_ms, end_ms, limit)
    return {"vehicle_id": vehicle_id, "estimates": rows}
