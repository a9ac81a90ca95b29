"""Every error of the HTTP API answers one JSON object, `{"detail": ...}` (`ErrorAnswer`), from one handler
(`error_answer`, installed by `install`), whatever raised it (`ANSWERS`):

| raised | by | status | detail |
| --- | --- | --- | --- |
| HTTPException | a route or dependency (401, 403, 404, 409, 413 for a body over the limit) | its own | its detail |
| RequestValidationError | FastAPI: the request does not match the OpenAPI (pydantic models, constrained parameters) | 422 | FastAPI's list of problems |
| the same, from a `Refused` | a rule of a request model, once the request matched the schema | 422 | the rule's sentence, naming where (`[1].profile.name: ...`) |
| PayloadError | the telemetry parser (roadgrip/cloud/ingest/wire.py) | 400, 413, 415 | a `Fault`: field, reason |
| ReportError | the station report parser (roadgrip/cloud/domain/stations.py) | 400, 413, 422 | a `ReportFault`: index, field, reason |
| ObservationError | the edge message parser (roadgrip/cloud/ingest/observations.py) | 400, 413, 422 | a `ReportFault`: index, field, reason |
| RateLimited | the vehicle's rate limit (roadgrip/cloud/ingest/ratelimit.py) | 429 with Retry-After; 413 when the request alone exceeds the burst | the reason |
| VehicleIdRefused | the backend: an id this mode cannot carry | 422 | the reason |
| StorageUnavailable, IngestUnavailable, BrokerUnavailable | the backend | 503 | what was not done |

Answers are ASCII JSON: they quote the input, and a lone surrogate that a JSON \\ud800 escape put there cannot be
written as UTF-8 (a 500, found by fuzzing: tests/cloud/test_fuzz.py).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable

from fastapi import FastAPI, Request
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from roadgrip.cloud.api.backend import VehicleIdRefused
from roadgrip.cloud.domain.stations import ReportError
from roadgrip.cloud.ingest.admission import IngestUnavailable, RateLimited
from roadgrip.cloud.ingest.observations import ObservationError
from roadgrip.cloud.ingest.wire import PayloadError
from roadgrip.cloud.storage.database import StorageUnavailable
from roadgrip.cloud.transport.rabbit_users import BrokerUnavailable


class Refused(ValueError):
    """A request that matches the OpenAPI schema but breaks a rule of the API, raised by a pydantic validator of a
    request model: 422, its message (which says where) as the detail."""


class Fault(BaseModel):
    field: str | None = Field(description="the part of the request at fault (content_type), or null")
    reason: str


class ReportFault(BaseModel):
    """A refused payload of station reports or of an edge vehicle's messages: the report or message (array index),
    the field and why; nothing was stored."""

    index: int | None
    field: str | None
    reason: str


class ErrorAnswer(BaseModel):
    """Every error: a sentence; for a telemetry body that cannot be read, the part at fault and why; for a station
    report refused, the report, field and why; for a request that does not match this schema, FastAPI's list of
    problems."""

    detail: str | Fault | ReportFault | list[dict]


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


def errors(*codes: int) -> dict:
    """OpenAPI `responses` for these error statuses (`ErrorAnswer` bodies)."""
    return {code: {"model": ErrorAnswer, "description": ERRORS[code]} for code in codes}


class AsciiJSONResponse(JSONResponse):
    def render(self, content) -> bytes:
        return json.dumps(content, ensure_ascii=True, allow_nan=False, separators=(",", ":")).encode("ascii")


def _invalid_request(exc: RequestValidationError) -> tuple[int, object, None]:
    problems = exc.errors()
    refused = problems[0].get("ctx", {}).get("error") if len(problems) == 1 else None
    return 422, str(refused) if isinstance(refused, Refused) else jsonable_encoder(problems), None


def _rate_limited(exc: RateLimited) -> tuple[int, str, dict | None]:
    if exc.retry_after_s == math.inf:  # the request alone exceeds the burst: it would never pass
        return 413, exc.reason, None
    return 429, exc.reason, {"Retry-After": str(math.ceil(exc.retry_after_s))}


# exception class -> (status, detail, headers); the table of the module docstring
ANSWERS: dict[type[Exception], Callable[[Exception], tuple[int, object, dict | None]]] = {
    StarletteHTTPException: lambda exc: (exc.status_code, exc.detail, exc.headers),
    RequestValidationError: _invalid_request,
    PayloadError: lambda exc: (exc.status, {"field": exc.field, "reason": str(exc)}, None),
    ReportError: lambda exc: (exc.status, exc.to_dict(), None),
    ObservationError: lambda exc: (exc.status, exc.to_dict(), None),
    RateLimited: _rate_limited,
    VehicleIdRefused: lambda exc: (422, str(exc), None),
    StorageUnavailable: lambda exc: (503, f"storage unavailable, nothing was stored: {exc}", None),
    BrokerUnavailable: lambda exc: (503, f"broker unavailable: {exc}", None),
    IngestUnavailable: lambda exc: (503, str(exc), None),
}


async def error_answer(request: Request, exc: Exception) -> AsciiJSONResponse:
    """The answer to an exception of a class in ANSWERS (or of a subclass)."""
    answer = next(ANSWERS[cls] for cls in type(exc).__mro__ if cls in ANSWERS)
    status, detail, headers = answer(exc)
    return AsciiJSONResponse({"detail": detail}, status_code=status, headers=headers)


def install(app: FastAPI) -> None:
    """Answer every exception of ANSWERS with `error_answer`."""
    for exc_class in ANSWERS:
        app.add_exception_handler(exc_class, error_answer)
