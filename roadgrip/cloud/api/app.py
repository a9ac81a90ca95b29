"""The HTTP API (FastAPI; OpenAPI at /docs). Routes are thin: they authenticate, check the role, and call the backend
(roadgrip/cloud/api/backend.py): the embedded service (`roadgrip serve`) or the cluster's (`roadgrip api`, any
number of replicas on one PostgreSQL and one RabbitMQ cluster: roadgrip/cloud/cluster/api_backend.py). The same routes serve
both; what differs in the cluster is said below the table.

Every call authenticates with HTTP Basic (name and secret; vehicles use their vehicle_id as name):

| route | who | does |
| --- | --- | --- |
| POST /v1/vehicles | admin | register a vehicle with its profile (DESIGN 3.2); returns its secret once |
| GET /v1/vehicles/{id} | admin, reader, the vehicle | its profile |
| POST /v1/readers | admin | create a reader credential; returns its secret once |
| POST /v1/stations | admin | register a roadside station (its own credential); returns its secret once |
| POST /v1/stations/{id}/reports | the station | its reports (roadgrip/cloud/domain/stations.py: one JSON object or an array) |
| GET /v1/stations | admin, reader | each station's newest report, with the evidence drawn from it and its cells |
| DELETE /v1/credentials/{name} | admin | revoke a credential, at once |
| POST /v1/telemetry | vehicle | ingest samples (DESIGN 3.1: NDJSON, a JSON array or object; wire v1 or VSS keys) |
| GET /v1/vehicles/{id}/estimates | admin, reader, the vehicle | estimates (DESIGN 3.4) over a time range |
| GET /v1/map | admin, reader | the friction map as GeoJSON |
| GET /v1/map/datex2 | admin, reader | the map as DATEX II v3 (RoadSurfaceConditionMeasurements, friction) |
| GET /v1/warnings | admin, reader, vehicles | slippery-road warnings as DENMs |
| GET /v1/health | anyone authenticated | storage, broker and pipeline state; 503 when storage is down |
| GET /metrics | anyone authenticated | Prometheus metrics (docs/CLOUD.md "Metrics (Prometheus)") |
| GET /v1/vehicles/latest | admin, reader | each vehicle's newest estimate and position (roadgrip.cloud.api.dashboard) |
| GET /dashboard | anyone (the page holds no data; it calls the API with a reader's credentials) | the live map |

Ingest answers 200 with counts and the rejected samples (index, field, reason) when at least one sample was valid, 422
when none was, 413 for an oversized body, 400 for a body that is not telemetry, 503 when storage is down (nothing
was stored: retry), 429 with Retry-After when the vehicle is over its rate limit (`roadgrip.cloud.ingest.ratelimit`, samples
a second, valid or not; nothing stored), and 413 for more samples in one request than the limit's whole burst.
Every error status of every route is declared in the OpenAPI document, with its body (`ErrorAnswer`); the schemathesis
tests of tests/cloud/test_fuzz.py hold the API to it.

In the cluster (docs/CLUSTER.md, "Stateless API"), a replica keeps nothing another replica needs:
- Credentials are read from PostgreSQL on every call (`Authenticator(revalidate=True)`): a credential revoked through
  any replica is refused by every replica from the next call on. Registering a vehicle (or a reader) also creates its
  RabbitMQ user with its permissions (roadgrip/cloud/transport/rabbit_users.py) before the database commits; revoking
  deletes the user, which closes its open MQTT connections. A vehicle's `mqtt_url` is the `mqtt` setting (the
  broker's load balancer); stations report over HTTP only (their `mqtt_url` is null).
- POST /v1/telemetry validates as above, then publishes the valid samples to amq.topic with the vehicle's telemetry
  routing key, as the vehicle's own MQTT publish would arrive, and answers **202** (`Accepted`) once the broker
  confirmed the message: it is in the vehicle's partition queue, replicated on a quorum of nodes, and a worker will
  store it; not "stored". 503 when no broker node confirmed it (retry: the worker stores a repeat once). The rate
  limit answered with 429 is this replica's own (a vehicle spread over N replicas gets up to N times it through
  them); the limit of the worker that owns the vehicle counts every replica's and MQTT's samples together and refuses
  the excess on the vehicle's MQTT errors topic.
- POST /v1/stations/{id}/reports: stored as embedded; the evidence of every report of the payload (a duplicate's as
  stored) is published to the owners of their regions (roadgrip/cloud/cluster/regions.py), which add it to the map and
  the warnings. 503 when no broker node confirmed it within 10 s: the reports are stored, send them again.
- GET /v1/map and /v1/map/datex2: the map the region owners saved (roadgrip/cloud/cluster/map_cells.py), at the
  replica's clock, read again when a second old; GET /v1/warnings: the stored warnings.
- GET /v1/health: storage and broker reachability; GET /metrics: the replica's own counters.
"""

from __future__ import annotations

import asyncio
import json
import math
import time
from typing import Annotated

from fastapi import Depends, FastAPI, HTTPException, Query, Request, Response
from fastapi import Path as PathParam
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.security import HTTPBasic, HTTPBasicCredentials
from prometheus_client import CONTENT_TYPE_PLAIN_0_0_4, generate_latest
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from roadgrip.cloud.api.backend import Accepted, ApiBackend, VehicleIdRefused
from roadgrip.cloud.api.dashboard import mount_dashboard
from roadgrip.cloud.domain.stations import ReportError, parse_reports
from roadgrip.cloud.formats.datex2 import datex2_xml
from roadgrip.cloud.formats.geojson import geojson
from roadgrip.cloud.ingest.admission import IngestUnavailable, RateLimited
from roadgrip.cloud.ingest.auth import AuthError
from roadgrip.cloud.ingest.wire import PayloadError, parse_payload
from roadgrip.cloud.metrics import registry_with
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import Credential, StorageUnavailable
from roadgrip.cloud.transport.rabbit_users import BrokerUnavailable
from roadgrip.data.telemetry import VEHICLE_ID_RE
from roadgrip.vehicle.params import VEHICLES, VehicleParams, vehicle_by_name

basic = HTTPBasic(description="name and secret (vehicles: vehicle_id and the secret from registration)")


RESERVED_IDS = ("latest",)  # path segments of /v1/vehicles/... that are not vehicles
MAX_MS = 2**63 - 1  # times are BIGINT columns: a larger bound would overflow the database driver (found by fuzzing)


class VehicleRegistration(BaseModel):
    vehicle_id: str = Field(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-, not 'latest'")
    profile: str | dict = Field("paper-suv", description=f"a known vehicle ({', '.join(VEHICLES)}) or a profile "
                                                         "mapping with the DESIGN 3.2 fields (SI)")


class ReaderRegistration(BaseModel):
    name: str = Field(pattern=VEHICLE_ID_RE.pattern)


class StationRegistration(BaseModel):
    station_id: str = Field(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-")


class StationAnswer(BaseModel):
    received: int
    stored: int = Field(description="new reports; a repeat of a stored one (same station_id and timestamp_ms) is a "
                                    "duplicate")
    duplicates: int
    evidence_cells: int = Field(description="H3 cells the new reports gave friction evidence to")


class ReportFault(BaseModel):
    """A refused payload of station reports: the report (array index), the field and why; nothing was stored."""
    index: int | None
    field: str | None
    reason: str


class Issued(BaseModel):
    name: str
    role: str
    secret: str = Field(description="shown once; stored only hashed")
    mqtt_url: str | None = None


class Rejection(BaseModel):
    """A refused sample (roadgrip.cloud.ingest.wire.SampleError)."""
    index: int = Field(description="array index, or NDJSON line number - 1")
    field: str | None = Field(description="the field at fault as sent (wire name or VSS key); null when the sample "
                                          "is not an object")
    reason: str
    vehicle_id: str | None = None
    timestamp_ms: int | None = None


class IngestAnswer(BaseModel):
    received: int
    accepted: int
    stored: int
    duplicates: int
    rejected: list[Rejection]


class PublishedAnswer(BaseModel):
    """Cluster mode: the valid samples are in the vehicle's partition queue, replicated; a worker stores them."""
    received: int
    accepted: int = Field(description="valid samples, confirmed by the broker")
    rejected: list[Rejection]


class NoValidSample(IngestAnswer):
    detail: str


class Fault(BaseModel):
    field: str | None = Field(description="the part of the request at fault (content_type), or null")
    reason: str


class ErrorAnswer(BaseModel):
    """Every error: a sentence; for a telemetry body that cannot be read, the part at fault and why; for a station
    report refused, the report, field and why; for a request that does not match this schema, FastAPI's list of
    problems."""
    detail: str | Fault | ReportFault | list[dict]


def _errors(*codes: int) -> dict:
    """OpenAPI `responses` for these error statuses (`ErrorAnswer` bodies)."""
    return {code: {"model": ErrorAnswer, "description": ERRORS[code]} for code in codes}


ERRORS = {
    400: "a body that cannot be read (not JSON, not UTF-8; telemetry: not JSON / NDJSON samples)",
    401: "no credentials, or invalid ones (unknown, wrong secret, revoked)",
    403: "this credential's role may not do this (a vehicle acting for another, a reader writing, ...)",
    404: "no such vehicle or credential",
    409: "the name is taken, or the credential cannot be revoked (the admin's)",
    413: "the body is over max_payload_bytes or max_samples_per_payload, or holds more samples than the vehicle's "
         "whole rate-limit burst",
    415: "a content type other than JSON or NDJSON",
    422: "the request does not match this schema",
    503: "storage unavailable: nothing was stored, retry; in the cluster also: the broker did not confirm the "
         "telemetry, or no broker node took a registration (nothing stored) or a revocation's user deletion (the "
         "credential is revoked; revoke again to delete the broker user)",
}


def _caller(request: Request, auth: Annotated[HTTPBasicCredentials, Depends(basic)]) -> Credential:
    if not VEHICLE_ID_RE.fullmatch(auth.username):  # no credential has such a name (PostgreSQL: a NUL was a 500)
        raise HTTPException(401, "invalid credentials", headers={"WWW-Authenticate": "Basic"})
    try:
        return request.app.state.service.auth.authenticate(auth.username, auth.password)
    except AuthError:
        raise HTTPException(401, "invalid credentials", headers={"WWW-Authenticate": "Basic"}) from None


Caller = Annotated[Credential, Depends(_caller)]
VehicleId = Annotated[str, PathParam(pattern=VEHICLE_ID_RE.pattern, description="1-64 of A-Za-z0-9_.-")]


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


def _escaped(rejection: dict) -> dict:
    """A rejection whose texts (the field as sent, the reason quoting the value) hold lone surrogates, which JSON
    escapes carry but UTF-8 cannot encode, with those written as \\udXXXX instead (they were a 500, found by fuzzing)."""
    return {k: v.encode("utf-8", "backslashreplace").decode("utf-8") if isinstance(v, str) else v
            for k, v in rejection.items()}


class AsciiJSONResponse(JSONResponse):
    def render(self, content) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


def single_query_values(request: Request) -> None:
    """Every query parameter this API declares is a scalar: one given twice (?limit=5&limit=7) is refused with 422, as
    the OpenAPI says, instead of being read as its last value (found by fuzzing: tests/cloud/test_fuzz.py). One place,
    for every route (a dependency of the app); parameters a route does not declare are ignored, as FastAPI does."""
    dependant = getattr(request.scope.get("route"), "dependant", None)
    declared = {param.alias for param in dependant.query_params} if dependant is not None else set()
    repeated = sorted(k for k in declared if len(request.query_params.getlist(k)) > 1)
    if repeated:
        raise RequestValidationError([{"type": "repeated_query_parameter", "loc": ("query", k),
                                       "msg": "a single value is expected, got several",
                                       "input": request.query_params.getlist(k)} for k in repeated])


def create_app(service: ApiBackend) -> FastAPI:
    app = FastAPI(title="roadgrip cloud", version="1",
                  description="Tire-road friction from connected-vehicle telemetry: ingest, estimates, map, warnings.",
                  responses=_errors(401, 403, 503),  # every route authenticates and reads storage
                  dependencies=[Depends(single_query_values)])
    app.state.service = service

    def require(caller: Credential, *roles: str) -> None:
        if caller.role not in roles:
            raise HTTPException(403, f"a {caller.role} credential may not do this (needs {' or '.join(roles)})")

    def may_read_vehicle(caller: Credential, vehicle_id: str) -> None:
        require(caller, "admin", "reader", "vehicle")  # a station reads no vehicle
        if caller.role == "vehicle" and caller.vehicle_id != vehicle_id:
            raise HTTPException(403, f"vehicle {caller.vehicle_id} may not read vehicle {vehicle_id}")

    # Errors answer in ASCII JSON: they quote the input, and a lone surrogate that a JSON \ud800 escape put there
    # cannot be written as UTF-8 (a 500, found by fuzzing: tests/cloud/test_fuzz.py).
    @app.exception_handler(RequestValidationError)
    async def invalid_request(request: Request, exc: RequestValidationError):
        return AsciiJSONResponse({"detail": jsonable_encoder(exc.errors())}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException):
        return AsciiJSONResponse({"detail": exc.detail}, status_code=exc.status_code, headers=exc.headers)

    @app.exception_handler(StorageUnavailable)
    async def storage_down(request: Request, exc: StorageUnavailable):
        return JSONResponse({"detail": f"storage unavailable, nothing was stored: {exc}"}, status_code=503)

    @app.exception_handler(BrokerUnavailable)
    async def broker_down(request: Request, exc: BrokerUnavailable):
        return JSONResponse({"detail": f"broker unavailable: {exc}"}, status_code=503)

    @app.post("/v1/vehicles", status_code=201, response_model=Issued | list[Issued], responses=_errors(400, 409, 422))
    def register_vehicles(body: VehicleRegistration | list[VehicleRegistration], caller: Caller):
        """One vehicle, or a list (a fleet at once: one broker reload); all or nothing."""
        require(caller, "admin")
        batch = body if isinstance(body, list) else [body]
        reserved = [item.vehicle_id for item in batch if item.vehicle_id in RESERVED_IDS]
        if reserved:
            raise HTTPException(422, f"vehicle_id {reserved[0]!r} is reserved (a route of the API)")
        profiles = []
        for k, item in enumerate(batch):
            try:
                profiles.append(vehicle_by_name(item.profile) if isinstance(item.profile, str)
                                else VehicleParams.from_dict(item.profile))
            except (ValueError, TypeError, KeyError) as exc:
                where = "profile" if not isinstance(body, list) else f"[{k}].profile"
                raise HTTPException(422, f"{where}: {exc}") from None
            where = _unstorable_text(profiles[-1].to_dict(), "profile" if not isinstance(body, list)
                                     else f"[{k}].profile")
            if where is not None:
                raise HTTPException(422, f"{where}: text with a NUL character or a lone surrogate cannot be stored")
        try:
            issued = service.register_vehicles([(item.vehicle_id, p) for item, p in zip(batch, profiles)])
        except VehicleIdRefused as exc:
            raise HTTPException(422, str(exc)) from None
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        answers = [Issued(name=item.vehicle_id, role="vehicle", secret=secret, mqtt_url=service.mqtt_url)
                   for item, secret in zip(batch, issued)]
        return answers if isinstance(body, list) else answers[0]

    @app.get("/v1/vehicles/{vehicle_id}", responses=_errors(404))
    def vehicle_profile(vehicle_id: VehicleId, caller: Caller) -> dict:
        may_read_vehicle(caller, vehicle_id)
        profile = service.storage.vehicle_profile(vehicle_id)
        if profile is None:
            raise HTTPException(404, f"no vehicle {vehicle_id!r}")
        return {"vehicle_id": vehicle_id, "profile": profile}

    @app.post("/v1/readers", status_code=201, response_model=Issued, responses=_errors(400, 409, 422))
    def register_reader(body: ReaderRegistration, caller: Caller) -> Issued:
        require(caller, "admin")
        try:
            secret = service.register_reader(body.name)
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        return Issued(name=body.name, role="reader", secret=secret, mqtt_url=service.mqtt_url)

    @app.post("/v1/stations", status_code=201, response_model=Issued, responses=_errors(400, 409, 422))
    def register_station(body: StationRegistration, caller: Caller) -> Issued:
        require(caller, "admin")
        try:
            secret = service.register_station(body.station_id)
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        return Issued(name=body.station_id, role="station", secret=secret, mqtt_url=service.station_mqtt_url)

    @app.post("/v1/stations/{station_id}/reports", response_model=StationAnswer, responses={
                  **_errors(413), 400: {"model": ErrorAnswer, "description": "a body that is not JSON"},
                  422: {"model": ErrorAnswer, "description": "a report breaks the format (detail: a ReportFault); "
                                                             "nothing stored"}},
              openapi_extra={"requestBody": {"required": True, "content": {"application/json": {"schema": {
                  "oneOf": [{"type": "object"}, {"type": "array", "items": {"type": "object"}}]}}}}})
    async def station_reports(station_id: VehicleId, request: Request, caller: Caller):
        require(caller, "station")
        if caller.name != station_id:
            raise HTTPException(403, f"station {caller.name} may not report for station {station_id}")
        s = service.settings
        body = await _read_limited(request, s.max_payload_bytes)
        try:
            reports = parse_reports(body, station_id=station_id, now_ms=int(time.time() * 1000),
                                    max_future_ms=int(s.max_future_s * 1000), max_bytes=s.max_payload_bytes)
        except ReportError as exc:
            raise HTTPException(exc.status, exc.to_dict()) from None
        result = await asyncio.to_thread(service.station_reports, reports)
        return StationAnswer(received=result.received, stored=result.stored, duplicates=result.duplicates,
                             evidence_cells=result.evidence_cells)

    @app.get("/v1/stations")
    def stations(caller: Caller) -> dict:
        """Each station's newest report (the fields of roadgrip/cloud/domain/stations.py), the evidence drawn from it (mu,
        mu_lower, mu_upper; null for none), its covered cells and received_ms; server_time_ms for the reports' age."""
        require(caller, "admin", "reader")
        return {"server_time_ms": int(time.time() * 1000), "stations": service.storage.latest_station_reports()}

    @app.delete("/v1/credentials/{name}", status_code=204, responses=_errors(404, 409))
    def revoke(name: Annotated[str, PathParam(pattern=VEHICLE_ID_RE.pattern)], caller: Caller) -> Response:
        require(caller, "admin")
        try:
            found = service.revoke(name)
        except ValueError as exc:
            raise HTTPException(409, str(exc)) from None
        if not found:
            raise HTTPException(404, f"no active credential {name!r}")
        return Response(status_code=204)

    @app.post("/v1/telemetry", response_model=IngestAnswer, responses={
                  **_errors(400, 413, 415),
                  202: {"model": PublishedAnswer, "description": "cluster mode: accepted by the broker and "
                                                                 "replicated, not yet stored"},
                  422: {"model": NoValidSample, "description": "no valid sample: each rejection says why"},
                  429: {"model": ErrorAnswer, "description": "the vehicle is over its rate limit: nothing stored",
                        "headers": {"Retry-After": {"description": "seconds until the same request would pass",
                                                    "schema": {"type": "integer"}}}}},
              openapi_extra={"requestBody": {"required": True, "content": {
                  "application/x-ndjson": {"schema": {"type": "string"}},
                  "application/json": {"schema": {"oneOf": [{"type": "object"},
                                                            {"type": "array", "items": {"type": "object"}}]}}}}})
    async def ingest(request: Request, caller: Caller):
        require(caller, "vehicle")
        try:
            samples, errors = await _read_telemetry(request, service.settings, caller.vehicle_id)
        except HTTPException:  # refused whole (400, 413, 415)
            service.http_payloads_rejected += 1
            raise
        rejected = [_escaped(e.to_dict()) for e in errors]
        received = len(samples) + len(errors)
        try:  # the rate limit first (all received count), then the samples stored
            result = await asyncio.wrap_future(service.submit_telemetry(caller.vehicle_id, samples, received))
        except RateLimited as exc:
            if exc.retry_after_s == math.inf:
                raise HTTPException(413, exc.reason) from None
            raise HTTPException(429, exc.reason, headers={"Retry-After": str(math.ceil(exc.retry_after_s))}) from None
        except StorageUnavailable as exc:
            raise HTTPException(503, f"storage unavailable, nothing was stored: {exc}") from None
        except IngestUnavailable as exc:
            raise HTTPException(503, str(exc)) from None
        if not samples:
            return AsciiJSONResponse({"detail": "no valid sample", "received": received, "accepted": 0, "stored": 0,
                                      "duplicates": 0, "rejected": rejected}, status_code=422)
        if isinstance(result, Accepted):
            return AsciiJSONResponse({"received": received, "accepted": result.samples, "rejected": rejected},
                                     status_code=202)
        return IngestAnswer(received=received, accepted=len(samples), stored=result.stored,
                            duplicates=result.duplicates, rejected=rejected)

    @app.get("/v1/vehicles/{vehicle_id}/estimates")
    def estimates(vehicle_id: VehicleId, caller: Caller,
                  start_ms: Annotated[int | None, Query(ge=0, le=MAX_MS, description="from (ms since epoch, "
                                                                                   "inclusive)")] = None,
                  end_ms: Annotated[int | None, Query(ge=0, le=MAX_MS, description="to (ms since epoch, "
                                                                                 "exclusive)")] = None,
                  limit: Annotated[int, Query(ge=1, le=100_000)] = 10_000) -> dict:
        may_read_vehicle(caller, vehicle_id)
        rows = service.storage.estimates(vehicle_id, start_ms, end_ms, limit)
        return {"vehicle_id": vehicle_id, "estimates": rows}

    @app.get("/v1/map")
    def friction_map(caller: Caller) -> dict:
        require(caller, "admin", "reader")
        friction_map, now = service.current_map()
        return geojson(friction_map.cells(now))

    @app.get("/v1/map/datex2", response_class=Response,
             responses={200: {"content": {"application/xml": {}}, "description": "DATEX II v3 publication"}})
    def datex2(caller: Caller) -> Response:
        require(caller, "admin", "reader")
        friction_map, now = service.current_map()
        return Response(datex2_xml(friction_map.cells(now), now), media_type="application/xml")

    @app.get("/v1/warnings")
    def warnings(caller: Caller, active: bool = True) -> dict:
        require(caller, "admin", "reader", "vehicle")
        rows = service.storage.warnings(active_only=active)
        return {"warnings": [row["message"]["denm"] for row in rows]}

    @app.get("/v1/health", responses={503: {"description": "storage unavailable (the body says so, as for 200)"}})
    def health(caller: Caller) -> JSONResponse:
        status = service.health()
        return JSONResponse(status, status_code=503 if status["status"] == "unavailable" else 200)

    registry = registry_with(service.metrics_collector())

    @app.get("/metrics", response_class=Response,
             responses={200: {"content": {"text/plain": {}},
                              "description": "Prometheus text exposition format (docs/CLOUD.md, \"Metrics\")"}})
    def metrics(caller: Caller) -> Response:
        """Prometheus metrics of this service and its ingest processes; who may read them: as /v1/health."""
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_PLAIN_0_0_4)

    mount_dashboard(app, service)
    return app


async def _read_telemetry(request: Request, s: Settings, vehicle_id: str) -> tuple[list[dict], list]:
    """A telemetry request's valid samples and rejections (roadgrip/cloud/ingest/wire.py); HTTPException (400, 413, 415) for
    a body refused whole."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > s.max_payload_bytes:
        raise HTTPException(413, f"body of {declared} bytes exceeds the limit of {s.max_payload_bytes}")
    body = await _read_limited(request, s.max_payload_bytes)
    try:
        return parse_payload(body, content_type=request.headers.get("content-type"), max_bytes=s.max_payload_bytes,
                             max_samples=s.max_samples_per_payload, now_ms=int(time.time() * 1000),
                             max_future_ms=int(s.max_future_s * 1000), vehicle_id=vehicle_id)
    except PayloadError as exc:
        raise HTTPException(exc.status, {"field": exc.field, "reason": str(exc)}) from None


async def _read_limited(request: Request, max_bytes: int) -> bytes:
    """The body, refusing it (413) as soon as it passes max_bytes: a client that lies about its length (or streams
    chunked) cannot make the service buffer more."""
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > max_bytes:
            raise HTTPException(413, f"body exceeds the limit of {max_bytes} bytes")
        chunks.append(chunk)
    return b"".join(chunks)
