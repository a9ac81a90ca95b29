"""The parser of edge vehicles' messages (CONTRACTS 3.7): friction observations and heartbeats
(`roadgrip.data.schema.OBSERVATION`, `HEARTBEAT`), from an HTTP body or an MQTT message.

A payload is one JSON object or an array of 1..MAX_PER_PAYLOAD of them, taken whole or not at all: the first fault
raises `ObservationError`, naming the message (index), the field and why, with the HTTP status to answer (400 not
JSON, 413 too large, 422 a message breaks the format). Rules beyond each field's type and range:
- no unknown field (the close name is suggested), no string for a number, no NaN or Infinity; integers for times and
  counts (a JSON number with no fraction is taken as one);
- vehicle_id is the credentials' vehicle;
- an observation's h3_cell is an H3 cell at the map's resolution that holds its position (roadgrip/cloud/domain/cells.py),
  first_ms <= last_ms, last_ms at most max_future_ms ahead of the server, 0 <= mu_lower <= mu <= mu_upper <= MU_MAX,
  1 <= n_estimates, 0 <= n_excited <= n_estimates, excited exactly when n_excited > 0, evidence of EVIDENCE_KINDS,
  channels among the optional telemetry fields (CONTRACTS 3.1);
- a heartbeat's timestamp_ms at most max_future_ms ahead of the server.
"""

from __future__ import annotations

import difflib

import h3
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.domain.checks import PayloadError, json_items
from roadgrip.cloud.domain.friction_map import MU_MAX
from roadgrip.cloud.settings import Settings
from roadgrip.data.schema import EVIDENCE_KINDS, TELEMETRY
from roadgrip.data.telemetry import VEHICLE_ID_RE

MAX_PER_PAYLOAD = 1_000
MAX_ESTIMATES_PER_PASS = 100_000  # 10,000 s at 10 Hz in one cell: more is no pass
CHANNELS = tuple(c.name for c in TELEMETRY if not c.required)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)


def _mu(**kwargs):
    return Field(ge=0.0, le=MU_MAX, allow_inf_nan=False, **kwargs)


class Observation(_Strict):
    vehicle_id: str = Field(pattern=VEHICLE_ID_RE.pattern)
    h3_cell: str = Field(min_length=1, max_length=16)
    first_ms: int = Field(ge=0)
    last_ms: int = Field(ge=0)
    latitude_deg: float = Field(ge=-90.0, le=90.0, allow_inf_nan=False)
    longitude_deg: float = Field(ge=-180.0, le=180.0, allow_inf_nan=False)
    mu: float = _mu()
    mu_lower: float = _mu()
    mu_upper: float = _mu()
    mu_proven: float | None = _mu(default=None)
    excited: bool
    n_estimates: int = Field(ge=1, le=MAX_ESTIMATES_PER_PASS)
    n_excited: int = Field(ge=0, le=MAX_ESTIMATES_PER_PASS)
    evidence: list[str] = Field(max_length=len(EVIDENCE_KINDS))
    channels: list[str] = Field(max_length=len(CHANNELS))
    vehicle_class: str = Field(pattern=VEHICLE_ID_RE.pattern)
    estimator: str = Field(min_length=1, max_length=64)


class Heartbeat(_Strict):
    vehicle_id: str = Field(pattern=VEHICLE_ID_RE.pattern)
    timestamp_ms: int = Field(ge=0)
    latitude_deg: float | None = Field(None, ge=-90.0, le=90.0, allow_inf_nan=False)
    longitude_deg: float | None = Field(None, ge=-180.0, le=180.0, allow_inf_nan=False)
    n_samples: int = Field(ge=0)
    n_observations: int = Field(ge=0)
    outbox_pending: int = Field(ge=0)
    outbox_dropped: int = Field(ge=0)


class ObservationError(PayloadError):
    """A payload of an edge vehicle refused: `index` (the message in an array; 0 for one object), `field` (None for
    the payload or the message as a whole) and the reason; `status` the HTTP status to answer."""

    NOUN = "message"


def _field_error(index: int, exc: ValidationError, model: type[BaseModel]) -> ObservationError:
    error = exc.errors()[0]
    field = ".".join(str(p) for p in error["loc"]) or None
    reason = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        close = difflib.get_close_matches(field, model.model_fields, n=1)
        reason = "unknown field" + (f" (did you mean {close[0]!r}?)" if close else "")
    elif "input" in error and error["type"] != "missing":
        reason += f", got {error['input']!r}"[:120]
    return ObservationError(reason, index=index, field=field)


def _items(body: bytes, max_bytes: int) -> list:
    return json_items(body, max_bytes=max_bytes, max_items=MAX_PER_PAYLOAD, error=ObservationError)


def _validated(model: type[BaseModel], index: int, item, integers: tuple[str, ...], vehicle_id: str):
    if not isinstance(item, dict):
        raise ObservationError(f"a message is a JSON object, got {type(item).__name__}", index=index)
    for name in integers:
        if isinstance(item.get(name), float) and item[name].is_integer():
            item[name] = int(item[name])  # JSON has one number type
    try:
        message = model.model_validate(item)
    except ValidationError as exc:
        raise _field_error(index, exc, model) from None
    if message.vehicle_id != vehicle_id:
        raise ObservationError(
            f"must be the vehicle of the credentials, {vehicle_id!r}, got {message.vehicle_id!r}",
            index=index,
            field="vehicle_id",
        )
    return message


def _future(t: int, now_ms: int, max_future_ms: int, index: int, field: str) -> None:
    if t > now_ms + max_future_ms:
        raise ObservationError(
            f"{t} is more than {max_future_ms / 1000:g} s ahead of the server's clock ({now_ms})",
            index=index,
            field=field,
        )


def _check_observation(o: Observation, index: int, resolution: int) -> None:
    def fault(field: str, reason: str) -> ObservationError:
        return ObservationError(reason, index=index, field=field)

    if not h3.is_valid_cell(o.h3_cell) or h3.get_resolution(o.h3_cell) != resolution:
        raise fault("h3_cell", f"must be an H3 cell at the map's resolution {resolution}, got {o.h3_cell!r}")
    if cell_of(o.latitude_deg, o.longitude_deg, resolution) != o.h3_cell:
        raise fault("latitude_deg", f"position ({o.latitude_deg}, {o.longitude_deg}) is not in cell {o.h3_cell}")
    if o.first_ms > o.last_ms:
        raise fault("first_ms", f"{o.first_ms} is after last_ms {o.last_ms}")
    if not o.mu_lower <= o.mu <= o.mu_upper:
        raise fault("mu", f"must lie in [mu_lower, mu_upper] = [{o.mu_lower}, {o.mu_upper}], got {o.mu}")
    if o.n_excited > o.n_estimates:
        raise fault("n_excited", f"{o.n_excited} is more than n_estimates {o.n_estimates}")
    if o.excited != (o.n_excited > 0):
        raise fault("excited", f"must be {o.n_excited > 0} with n_excited {o.n_excited}, got {o.excited}")
    for name, given, allowed in (("evidence", o.evidence, EVIDENCE_KINDS), ("channels", o.channels, CHANNELS)):
        unknown = [v for v in given if v not in allowed]
        if unknown or len(set(given)) != len(given):
            raise fault(name, f"must be distinct values of {list(allowed)}, got {given!r}")


def parse_observations(
    body: bytes, *, vehicle_id: str, resolution: int, now_ms: int, max_future_ms: int = 60_000, max_bytes: int = 65_536
) -> list[dict]:
    """The observations (dicts of OBSERVATION_FIELDS) of a payload of `vehicle_id` (module docstring)."""
    out = []
    for index, item in enumerate(_items(body, max_bytes)):
        o = _validated(Observation, index, item, ("first_ms", "last_ms", "n_estimates", "n_excited"), vehicle_id)
        _check_observation(o, index, resolution)
        _future(o.last_ms, now_ms, max_future_ms, index, "last_ms")
        out.append(o.model_dump())
    return out


def parse_heartbeats(
    body: bytes, *, vehicle_id: str, now_ms: int, max_future_ms: int = 60_000, max_bytes: int = 65_536
) -> list[dict]:
    """The heartbeats (dicts of HEARTBEAT_FIELDS) of a payload of `vehicle_id` (module docstring)."""
    out = []
    integers = ("timestamp_ms", "n_samples", "n_observations", "outbox_pending", "outbox_dropped")
    for index, item in enumerate(_items(body, max_bytes)):
        h = _validated(Heartbeat, index, item, integers, vehicle_id)
        _future(h.timestamp_ms, now_ms, max_future_ms, index, "timestamp_ms")
        out.append(h.model_dump())
    return out


def parse_edge_message(kind: str, body: bytes, *, vehicle_id: str, settings: Settings, now_ms: int) -> list[dict]:
    """The observations (kind "observations") or heartbeats (kind "heartbeat") of one message of `vehicle_id`, checked
    with the service's settings (H3 resolution, max_future_s, max_payload_bytes); ObservationError for the first fault."""
    limits = {
        "now_ms": now_ms,
        "max_future_ms": int(settings.max_future_s * 1000),
        "max_bytes": settings.max_payload_bytes,
    }
    if kind == "observations":
        return parse_observations(body, vehicle_id=vehicle_id, resolution=settings.h3_resolution, **limits)
    return parse_heartbeats(body, vehicle_id=vehicle_id, **limits)
