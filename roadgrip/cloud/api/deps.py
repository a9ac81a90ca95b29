"""What every route of the HTTP API shares, as FastAPI dependencies on `app.state` (set once by create_app,
roadgrip/cloud/api/app.py): the backend (roadgrip/cloud/api/backend.py), its settings and authenticator, the metrics
registry; the caller (HTTP Basic) and the role checks; the path parameter of a name; the body read with its size limit;
and the app-wide rule that a query parameter is given once.

Authentication is a dependency (401 before anything else of the route is looked at); the role check is the route's
first line (`require`, `may_read_vehicle`), after FastAPI validated the request: a malformed request is a 422 whoever
sends it, as it always was.
"""

from __future__ import annotations

import re
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.security import HTTPBasic, HTTPBasicCredentials
from prometheus_client import CollectorRegistry
from pydantic import BeforeValidator

from roadgrip.cloud.api.backend import ApiBackend
from roadgrip.cloud.ingest.auth import Authenticator, AuthError
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Credential
from roadgrip.data.telemetry import VEHICLE_ID_RE

basic = HTTPBasic(description="name and secret (vehicles: vehicle_id and the secret from registration)")


async def get_backend(request: Request) -> ApiBackend:
    return request.app.state.backend


Backend = Annotated[ApiBackend, Depends(get_backend)]


async def get_settings(backend: Backend) -> Settings:
    return backend.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


async def get_authenticator(backend: Backend) -> Authenticator:
    return backend.auth


async def get_metrics_registry(request: Request) -> CollectorRegistry:
    return request.app.state.metrics_registry


MetricsRegistry = Annotated[CollectorRegistry, Depends(get_metrics_registry)]


def get_caller(
    auth: Annotated[HTTPBasicCredentials, Depends(basic)],
    authenticator: Annotated[Authenticator, Depends(get_authenticator)],
) -> Credential:
    """The credential of the request (401 for none, an unknown one, a wrong secret or a revoked credential); a plain
    function: the authenticator may read storage, so FastAPI runs it in its thread pool."""
    if not VEHICLE_ID_RE.fullmatch(auth.username):  # no credential has such a name (PostgreSQL: a NUL was a 500)
        raise HTTPException(401, "invalid credentials", headers={"WWW-Authenticate": "Basic"})
    try:
        return authenticator.authenticate(auth.username, auth.password)
    except AuthError:
        raise HTTPException(401, "invalid credentials", headers={"WWW-Authenticate": "Basic"}) from None


Caller = Annotated[Credential, Depends(get_caller)]
VehicleId = Annotated[str, PathParam(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-")]


def require(caller: Credential, *roles: str) -> None:
    """403 unless the caller has one of `roles`."""
    if caller.role not in roles:
        raise HTTPException(403, f"a {caller.role} credential may not do this (needs {' or '.join(roles)})")


def may_read_vehicle(caller: Credential, vehicle_id: str) -> None:
    """403 unless the caller may read this vehicle's data: the admin, a reader, the vehicle itself."""
    require(caller, "admin", "reader", "vehicle")  # a station reads no vehicle
    if caller.role == "vehicle" and caller.vehicle_id != vehicle_id:
        raise HTTPException(403, f"vehicle {caller.vehicle_id} may not read vehicle {vehicle_id}")


async def read_limited(request: Request, max_bytes: int) -> bytes:
    """The body, refusing it (413) as soon as it passes max_bytes: a client that lies about its length (or streams
    chunked) cannot make the service buffer more."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise HTTPException(413, f"body exceeds the limit of {max_bytes} bytes")
        chunks.append(chunk)
    return b"".join(chunks)


def single_query_values(request: Request) -> None:
    """Every query parameter this API declares is a scalar: one given twice (?limit=5&limit=7) is refused with 422, as
    the OpenAPI says, instead of being read as its last value (found by fuzzing: tests/cloud/test_fuzz.py). One place,
    for every route (a dependency of the app); parameters a route does not declare are ignored, as FastAPI does."""
    dependant = getattr(request.scope.get("route"), "dependant", None)
    declared = {param.alias for param in dependant.query_params} if dependant is not None else set()
    repeated = sorted(k for k in declared if len(request.query_params.getlist(k)) > 1)
    if repeated:
        raise RequestValidationError(
            [
                {
                    "type": "repeated_query_parameter",
                    "loc": ("query", k),
                    "msg": "a single value is expected, got several",
                    "input": request.query_params.getlist(k),
                }
                for k in repeated
            ]
        )


_DIGITS = re.compile(r"[+-]?[0-9]+")


def _integer_text(value):
    """A query parameter declared an integer is written as one: pydantic's lax mode would take "0.0" or "1e3" (a
    float's text) as an int, which the OpenAPI document says is not an integer (the fuzzer sends such values)."""
    if isinstance(value, str) and not _DIGITS.fullmatch(value):
        raise ValueError(f"must be an integer written in digits, got {value!r}")
    return value


QueryInt = BeforeValidator(_integer_text)  # Annotated[int, QueryInt, Query(...)]: an integer query parameter
