"""POST /v1/observations and POST /v1/heartbeats: an edge vehicle's friction observations and heartbeats (CONTRACTS
3.7: one JSON object or an array), read by roadgrip/cloud/ingest/observations.py and handed to the backend. The same
credentials as telemetry: a vehicle sends only its own (vehicle_id of every message = the caller's name).

Answers 200 with counts; 422 naming the message (index), the field and why when one breaks the format (nothing
stored), 400 for a body that is not JSON, 413 for one over the limit, 503 when storage is down (nothing stored)."""

import asyncio
import time

from fastapi import APIRouter, Request
from pydantic import BaseModel, Field

from roadgrip.cloud.api.deps import Backend, Caller, read_limited, require
from roadgrip.cloud.api.errors import ErrorAnswer, errors
from roadgrip.cloud.ingest.observations import parse_heartbeats, parse_observations

router = APIRouter()


class EdgeAnswer(BaseModel):
    received: int
    stored: int = Field(description="new ones; a repeat of a stored one (same vehicle_id and time) is a duplicate")
    duplicates: int


RESPONSES = {
    **errors(413),
    400: {"model": ErrorAnswer, "description": "a body that is not JSON"},
    422: {
        "model": ErrorAnswer,
        "description": "a message breaks the format (detail: index, field, reason); none stored",
    },
}
BODY = {
    "requestBody": {
        "required": True,
        "content": {
            "application/json": {
                "schema": {"oneOf": [{"type": "object"}, {"type": "array", "items": {"type": "object"}}]}
            }
        },
    }
}


@router.post("/v1/observations", response_model=EdgeAnswer, responses=RESPONSES, openapi_extra=BODY)
async def observations(request: Request, caller: Caller, backend: Backend):
    require(caller, "vehicle")
    s = backend.settings
    parsed = parse_observations(
        await read_limited(request, s.max_payload_bytes),
        vehicle_id=caller.name,
        resolution=s.h3_resolution,
        now_ms=int(time.time() * 1000),
        max_future_ms=int(s.max_future_s * 1000),
        max_bytes=s.max_payload_bytes,
    )
    result = await asyncio.to_thread(backend.observations, parsed)
    return EdgeAnswer(received=result.received, stored=result.stored, duplicates=result.duplicates)


@router.post("/v1/heartbeats", response_model=EdgeAnswer, responses=RESPONSES, openapi_extra=BODY)
async def heartbeats(request: Request, caller: Caller, backend: Backend):
    require(caller, "vehicle")
    s = backend.settings
    parsed = parse_heartbeats(
        await read_limited(request, s.max_payload_bytes),
        vehicle_id=caller.name,
        now_ms=int(time.time() * 1000),
        max_future_ms=int(s.max_future_s * 1000),
        max_bytes=s.max_payload_bytes,
    )
    result = await asyncio.to_thread(backend.heartbeats, parsed)
    return EdgeAnswer(received=result.received, stored=result.stored, duplicates=result.duplicates)
