"""Roadside stations' reports (roadgrip/cloud/domain/stations.py: one JSON object or an array), and each station's
newest report with the evidence drawn from it (registration: routes/credentials.py)."""

import asyncio
import time

from fastapi import APIRouter, HTTPException, Request
from pydantic import BaseModel, Field

from roadgrip.cloud.api.deps import Backend, Caller, VehicleId, read_limited, require
from roadgrip.cloud.api.errors import ErrorAnswer, errors
from roadgrip.cloud.domain.stations import parse_reports

router = APIRouter()


class StationAnswer(BaseModel):
    received: int
    stored: int = Field(
        description="new reports; a repeat of a stored one (same station_id and timestamp_ms) is a duplicate"
    )
    duplicates: int
    evidence_cells: int = Field(description="H3 cells the new reports gave friction evidence to")


@router.post(
    "/v1/stations/{station_id}/reports",
    response_model=StationAnswer,
    responses={
        **errors(413),
        400: {"model": ErrorAnswer, "description": "a body that is not JSON"},
        422: {
            "model": ErrorAnswer,
            "description": "a report breaks the format (detail: a ReportFault); nothing stored",
        },
    },
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {
                "application/json": {
                    "schema": {"oneOf": [{"type": "object"}, {"type": "array", "items": {"type": "object"}}]}
                }
            },
        }
    },
)
async def station_reports(station_id: VehicleId, request: Request, caller: Caller, backend: Backend):
    require(caller, "station")
    if caller.name != station_id:
        raise HTTPException(403, f"station {caller.name} may not report for station {station_id}")
    s = backend.settings
    body = await read_limited(request, s.max_payload_bytes)
    reports = parse_reports(
        body,
        station_id=station_id,
        now_ms=int(time.time() * 1000),
        max_future_ms=int(s.max_future_s * 1000),
        max_bytes=s.max_payload_bytes,
    )
    result = await asyncio.to_thread(backend.station_reports, reports)
    return StationAnswer(
        received=result.received,
        stored=result.stored,
        duplicates=result.duplicates,
        evidence_cells=result.evidence_cells,
    )


@router.get("/v1/stations")
def stations(caller: Caller, backend: Backend) -> dict:
    """Each station's newest report (the fields of roadgrip/cloud/domain/stations.py), the evidence drawn from it (mu,
    mu_lower, mu_upper; null for none), its covered cells and received_ms; server_time_ms for the reports' age."""
    require(caller, "admin", "reader")
    return {"server_time_ms": int(time.time() * 1000), "stations": backend.storage.latest_station_reports()}
