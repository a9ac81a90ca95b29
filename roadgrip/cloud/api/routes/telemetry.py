"""POST /v1/telemetry: a vehicle's samples (CONTRACTS 3.1: NDJSON, a JSON array or object; wire v1 or VSS keys), read by
the wire parser (roadgrip/cloud/ingest/wire.py) and handed to the backend.

Ingest answers 200 with counts and the rejected samples (index, field, reason) when at least one sample was valid, 422
when none was, 413 for an oversized body, 400 for a body that is not telemetry, 503 when storage is down (nothing
was stored: retry), 429 with Retry-After when the vehicle is over its rate limit (`roadgrip.cloud.ingest.ratelimit`,
samples a second, valid or not; nothing stored), and 413 for more samples in one request than the limit's whole burst.
In the cluster: 202 once the broker confirmed the samples (roadgrip/cloud/api/app.py)."""

import asyncio
import time

from fastapi import APIRouter, HTTPException, Request
from pydantic import BaseModel, Field

from roadgrip.cloud.api.backend import Accepted
from roadgrip.cloud.api.deps import Backend, Caller, read_limited, require
from roadgrip.cloud.api.errors import AsciiJSONResponse, ErrorAnswer, errors
from roadgrip.cloud.ingest.wire import PayloadError, SampleError, encodable, parse_payload
from roadgrip.cloud.settings import Settings

router = APIRouter()


class Rejection(BaseModel):
    """A refused sample (roadgrip.cloud.ingest.wire.SampleError)."""

    index: int = Field(description="array index, or NDJSON line number - 1")
    field: str | None = Field(
        description="the field at fault as sent (wire name or VSS key); null when the sample is not an object"
    )
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


@router.post(
    "/v1/telemetry",
    response_model=IngestAnswer,
    responses={
        **errors(400, 413, 415),
        202: {
            "model": PublishedAnswer,
            "description": "cluster mode: accepted by the broker and replicated, not yet stored",
        },
        422: {"model": NoValidSample, "description": "no valid sample: each rejection says why"},
        429: {
            "model": ErrorAnswer,
            "description": "the vehicle is over its rate limit: nothing stored",
            "headers": {
                "Retry-After": {
                    "description": "seconds until the same request would pass",
                    "schema": {"type": "integer"},
                }
            },
        },
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/x-ndjson": {"schema": {"type": "string"}},
                "application/vnd.apache.arrow.stream": {"schema": {"type": "string", "format": "binary"}},
                "application/json": {
                    "schema": {"oneOf": [{"type": "object"}, {"type": "array", "items": {"type": "object"}}]}
                },
            },
        }
    },
)
async def ingest(request: Request, caller: Caller, backend: Backend):
    require(caller, "vehicle")
    try:
        samples, faults = await _read_telemetry(request, backend.settings, caller.vehicle_id)
    except (HTTPException, PayloadError):  # refused whole (400, 413, 415)
        backend.http_payloads_rejected += 1
        raise
    rejected = [_escaped(e.to_dict()) for e in faults]
    received = len(samples) + len(faults)
    # the rate limit first (all received count), then the samples stored; RateLimited (429, 413), StorageUnavailable
    # and IngestUnavailable (503) answer as roadgrip/cloud/api/errors.py says
    result = await asyncio.wrap_future(backend.submit_telemetry(caller.vehicle_id, samples, received))
    if not samples:
        return AsciiJSONResponse(
            {
                "detail": "no valid sample",
                "received": received,
                "accepted": 0,
                "stored": 0,
                "duplicates": 0,
                "rejected": rejected,
            },
            status_code=422,
        )
    if isinstance(result, Accepted):
        return AsciiJSONResponse(
            {"received": received, "accepted": result.samples, "rejected": rejected}, status_code=202
        )
    return IngestAnswer(
        received=received, accepted=len(samples), stored=result.stored, duplicates=result.duplicates, rejected=rejected
    )


async def _read_telemetry(request: Request, s: Settings, vehicle_id: str) -> tuple[list[dict], list[SampleError]]:
    """A telemetry request's valid samples and rejections (roadgrip/cloud/ingest/wire.py); HTTPException (413) for a
    body over the limit, PayloadError (400, 413, 415) for one the parser refuses whole."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > s.max_payload_bytes:
        raise HTTPException(413, f"body of {declared} bytes exceeds the limit of {s.max_payload_bytes}")
    body = await read_limited(request, s.max_payload_bytes)
    return parse_payload(
        body,
        content_type=request.headers.get("content-type"),
        max_bytes=s.max_payload_bytes,
        max_samples=s.max_samples_per_payload,
        now_ms=int(time.time() * 1000),
        max_future_ms=int(s.max_future_s * 1000),
        vehicle_id=vehicle_id,
    )


def _escaped(rejection: dict) -> dict:
    """A rejection whose texts (the field as sent, the reason quoting the value) hold lone surrogates, which JSON
    escapes carry but UTF-8 cannot encode, with those written as \\udXXXX instead (they were a 500, found by
    fuzzing)."""
    return {k: encodable(v) if isinstance(v, str) else v for k, v in rejection.items()}
