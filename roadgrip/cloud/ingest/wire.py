"""Telemetry payloads as they reach the cloud (HTTP bodies, MQTT messages): parsed and validated sample by sample.

`parse_payload(body, content_type=..., now_ms=..., vehicle_id=...)` returns `(samples, errors)`: the valid samples, in
payload order, as dicts with exactly the wire format v1 names (`roadgrip.data.schema.TELEMETRY`, CONTRACTS 3.1) holding
Python floats, ints, bools and strings, and one `SampleError` per refused sample. A payload that cannot be read at all
raises `PayloadError`, which carries the HTTP status to answer.

The payload (`PayloadError` when a rule fails):
- at most `max_bytes` (413, checked before anything is decoded); UTF-8 (a leading byte order mark is skipped);
- content type `application/json`: one JSON object (one sample) or an array of samples; `application/x-ndjson`,
  `application/jsonl` and their usual aliases (`NDJSON_TYPES`): one object per line, blank lines (nothing but spaces,
  tabs, CR) ignored; parameters such as `; charset=utf-8` are ignored; any other type is refused (415). No content type
  (MQTT): an array when the first non-blank character is `[`, else one object when the whole body parses as one, else
  NDJSON;
- content type `application/vnd.apache.arrow.stream` (`ARROW_TYPES`), or no content type and a first byte 0xFF
  (`is_arrow`): an Arrow IPC stream of wire columns (CONTRACTS 3.1), checked column by column on numpy arrays
  (`_arrow_table`): refused whole when it cannot be read, names a column that is not a wire field, gives one a type of
  another kind, lacks a required column or holds no row; then each row by the rules below (the same messages), a null
  in a required column refusing its row. `arrow_payload` writes such a stream;
- a JSON document that does not parse or is neither an object nor an array is refused (we cannot tell where its samples
  start); in NDJSON a bad line is a `SampleError` for that line and the other lines are kept;
- at least one sample (an empty body, only blank lines or `[]` are refused) and at most `max_samples` (413: the payload
  is too large, in samples rather than bytes).

Each sample (`SampleError`, with its first fault; `index` is its array index, or its line number - 1 in NDJSON):
1. is a JSON object;
2. has wire format v1 keys only (strict: an unknown key is an error naming it, with the close wire name when there is
   one; `t_s`, which files may use, is not accepted on the wire), or COVESA VSS keys (any key starting with "Vehicle."
   makes the sample VSS; `VSS` below maps them, converting units) with `timestamp_ms` and `vehicle_id` allowed as plain
   keys beside them (VSS has no sample time). Other wire keys mixed with VSS keys are an error (a key known to neither
   is reported first, as unknown). Errors on a VSS sample
   name the VSS key that was sent and give its value and range in the VSS unit;
3. has every required field (TELEMETRY required=True: all but latitude, longitude, lateral speed, the tcs_active and
   esc_active flags and the optional channels of `OPTIONAL_CHANNELS`: GNSS speed, forces, steering torques); a sample
   without
   vehicle_id takes the payload's authenticated vehicle when there is one;
4. then field by field, vehicle_id, timestamp_ms, then the schema order:
   - vehicle_id: a string matching `VEHICLE_ID_RE`; when the authenticated `vehicle_id` is given, that one;
   - timestamp_ms: an integer >= 0 and at most `max_future_ms` ahead of `now_ms`. JSON has one number type and some
     encoders write 1.7e12 or 1700000000000.0: an integral float is accepted; a fractional one is refused;
   - numbers: JSON numbers (a boolean or a string is not a number), finite (Python's json reads the literals NaN and
     Infinity: they are refused), inside their physical range (`roadgrip.data.telemetry.RANGES`);
   - booleans: JSON true or false only;
   - the optional fields may be null or absent: None in the output; null in a required field is an error.

Not this module's business: duplicates inside a payload are kept (the pipeline and storage handle them); a key repeated
inside one JSON object keeps its last value, as `json.loads` does.

Size: over 500 lines because the wire format's one parser: JSON, NDJSON, Arrow and VSS keys, per-sample checks and the
rejection report, each rule once.
"""

from __future__ import annotations

import difflib
import json
import math
import numbers
import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import orjson
import pyarrow as pa

from roadgrip.data.schema import TELEMETRY
from roadgrip.data.telemetry import RANGES, TELEMETRY_SCHEMA, VEHICLE_ID_RE
from roadgrip.units import deg_to_rad, kmh_to_mps, mps_to_kmh, rad_to_deg

JSON_TYPES = frozenset({"application/json"})
ARROW_TYPES = frozenset({"application/vnd.apache.arrow.stream"})  # the IANA-registered type of the IPC stream
NDJSON_TYPES = frozenset(
    {
        "application/x-ndjson",
        "application/ndjson",
        "application/jsonl",
        "application/x-jsonl",
        "application/jsonlines",
        "application/x-jsonlines",
    }
)
_JSON_SPACE = " \t\r"  # JSON's whitespace, less the newline that ends an NDJSON line
_OBJECTS_IN_A_ROW = re.compile(r"\}[ \t\r]*,[ \t\r]*\{")
CLIP_CHARS = 40  # values and keys quoted in messages are cut to this many characters


@dataclass(frozen=True)
class VssSignal:
    """A COVESA VSS signal that maps to a wire field: `to_si` converts its unit (None: already the wire unit)."""

    wire: str
    unit: str
    to_si: Callable[[float], float] | None = None
    from_si: Callable[[float], float] | None = None


_WHEEL_AXLES = {"fl": "Row1.Wheel.Left", "fr": "Row1.Wheel.Right", "rl": "Row2.Wheel.Left", "rr": "Row2.Wheel.Right"}

# CONTRACTS 3.1: VSS key -> wire field.
VSS = {
    "Vehicle.VehicleIdentification.VIN": VssSignal("vehicle_id", "-"),
    "Vehicle.CurrentLocation.Latitude": VssSignal("latitude_deg", "deg"),
    "Vehicle.CurrentLocation.Longitude": VssSignal("longitude_deg", "deg"),
    "Vehicle.Speed": VssSignal("speed_mps", "km/h", kmh_to_mps, mps_to_kmh),
    "Vehicle.Acceleration.Longitudinal": VssSignal("accel_lon_mps2", "m/s^2"),
    "Vehicle.Acceleration.Lateral": VssSignal("accel_lat_mps2", "m/s^2"),
    "Vehicle.AngularVelocity.Yaw": VssSignal("yaw_rate_radps", "deg/s", deg_to_rad, rad_to_deg),
    "Vehicle.Chassis.SteeringWheel.Angle": VssSignal("steering_wheel_angle_rad", "deg", deg_to_rad, rad_to_deg),
    **{
        f"Vehicle.Chassis.Axle.{axle}.AngularSpeed": VssSignal(
            f"wheel_speed_{w}_radps", "deg/s", deg_to_rad, rad_to_deg
        )
        for w, axle in _WHEEL_AXLES.items()
    },
    "Vehicle.ADAS.ABS.IsEngaged": VssSignal("abs_active", "-"),
    "Vehicle.ADAS.CruiseControl.IsActive": VssSignal("acc_active", "-"),
    "Vehicle.ADAS.TCS.IsEngaged": VssSignal("tcs_active", "-"),
    "Vehicle.ADAS.ESC.IsEngaged": VssSignal("esc_active", "-"),
    "Vehicle.MotionManagement.Steering.SteeringWheel.Torque": VssSignal("steering_torque_nm", "N m"),
}
VSS_PLAIN_KEYS = ("timestamp_ms", "vehicle_id")  # wire keys allowed beside VSS keys


class PayloadError(ValueError):
    """The whole payload is unusable; `status` is the HTTP status to answer (400, 413 or 415), `field` the part at fault
    when there is one (`content_type`)."""

    def __init__(self, message: str, *, status: int = 400, field: str | None = None):
        super().__init__(message)
        self.status = status
        self.field = field


@dataclass(frozen=True)
class SampleError:
    """One refused sample: its position in the payload (array index, or line number - 1 in NDJSON), the field at fault
    (wire name or the VSS key sent; None when the sample is not an object), why, and the sample's vehicle and time when
    they could be read."""

    index: int
    field: str | None
    reason: str
    vehicle_id: str | None = None
    timestamp_ms: int | None = None

    def to_dict(self) -> dict:
        return {
            "index": self.index,
            "field": self.field,
            "reason": self.reason,
            "vehicle_id": self.vehicle_id,
            "timestamp_ms": self.timestamp_ms,
        }


def parse_payload(
    body: bytes,
    *,
    content_type: str | None = None,
    max_bytes: int = 1_048_576,
    max_samples: int = 10_000,
    now_ms: int,
    max_future_ms: int = 60_000,
    vehicle_id: str | None = None,
) -> tuple[list[dict], list[SampleError]]:
    """Parse and validate a payload of telemetry (the rules are in the module docstring).

    `now_ms` is the server clock (ms since the Unix epoch); `vehicle_id` the vehicle whose credentials sent the payload
    (None: any vehicle, and every sample must name its own). Returns (valid samples, one SampleError per refused sample);
    raises PayloadError when the payload as a whole cannot be used."""
    _check_options(body, max_bytes, max_samples, now_ms, max_future_ms, vehicle_id)
    if len(body) > max_bytes:
        raise PayloadError(f"payload of {len(body)} bytes exceeds the limit of {max_bytes} bytes", status=413)
    kind = _kind(content_type)
    if kind == "arrow" or (kind is None and is_arrow(body)):
        table, errors = _arrow_table(bytes(body), max_samples, int(now_ms), int(max_future_ms), vehicle_id)
        return table.to_pylist(), errors
    try:
        text = body.decode("utf-8")
    except UnicodeDecodeError as e:
        raise PayloadError(f"payload is not UTF-8: {e.reason} at byte {e.start}") from None
    text = text.removeprefix("\ufeff")
    if not text.strip():
        raise PayloadError("empty payload: no samples")
    docs, numbers = _documents(text, kind, max_samples)

    check = _Checker(int(now_ms), int(max_future_ms), vehicle_id).check
    samples, errors = [], []
    for i, doc in enumerate(docs):
        try:
            samples.append(check(doc))
        except _Refused as e:
            vid, ts = _identity(doc, vehicle_id)
            errors.append(SampleError(numbers[i] if numbers else i, e.field, e.reason, vid, ts))
    return samples, errors


# ------------------------------------------------------------------------------------------------- the payload


def _check_options(body, max_bytes, max_samples, now_ms, max_future_ms, vehicle_id) -> None:
    if not isinstance(body, (bytes, bytearray)):
        raise TypeError(f"body must be bytes, got {type(body).__name__}")
    for name, value, low in (
        ("max_bytes", max_bytes, 1),
        ("max_samples", max_samples, 1),
        ("now_ms", now_ms, 0),
        ("max_future_ms", max_future_ms, 0),
    ):
        if (
            type(value) is not int
            and (isinstance(value, bool) or not isinstance(value, numbers.Integral))
            or value < low
        ):
            raise ValueError(f"{name} must be an integer >= {low}, got {value!r}")
    if vehicle_id is not None and not (isinstance(vehicle_id, str) and VEHICLE_ID_RE.fullmatch(vehicle_id)):
        raise ValueError(f"vehicle_id must be None or match {VEHICLE_ID_RE.pattern}, got {vehicle_id!r}")


def _kind(content_type: str | None) -> str | None:
    """'json', 'ndjson', 'arrow', or None (detect) from a Content-Type value."""
    if content_type is None or not content_type.strip():
        return None
    media = content_type.split(";", 1)[0].strip().lower()
    if media in JSON_TYPES:
        return "json"
    if media in NDJSON_TYPES:
        return "ndjson"
    if media in ARROW_TYPES:
        return "arrow"
    raise PayloadError(
        f"content type {_clip(content_type)!r} is not accepted: send application/json (an object or an "
        "array), application/x-ndjson (one object per line) or application/vnd.apache.arrow.stream (an Arrow IPC "
        "stream of wire columns)",
        status=415,
        field="content_type",
    )


def _documents(text: str, kind: str | None, max_samples: int) -> tuple[list, list[int] | None]:
    """(one parsed value per sample, each one's index when that is not its position: NDJSON line numbers - 1 when
    blank lines were left out). A bad NDJSON line is a `_BadLine`."""
    if kind is None:
        if text.lstrip()[:1] == "[":
            kind = "json"
        else:
            try:
                doc = _loads(text)
            except (ValueError, RecursionError):
                kind = "ndjson"
            else:
                return _json_samples(doc, max_samples), None
    if kind == "json":
        try:
            doc = _loads(text)
        except json.JSONDecodeError as e:
            hint = " (one object per line is NDJSON: send it as application/x-ndjson)" if e.msg == "Extra data" else ""
            raise PayloadError(
                f"payload is not valid JSON: {e.msg} at line {e.lineno} column {e.colno}{hint}"
            ) from None
        except (
            ValueError,
            RecursionError,
        ) as e:  # json's limit on integer digits, or nesting deeper than Python's stack
            raise PayloadError(f"payload is not valid JSON: {_json_failure(e)}") from None
        return _json_samples(doc, max_samples), None

    lines = [line.strip(_JSON_SPACE) for line in text.split("\n")]
    while lines and not lines[-1]:
        lines.pop()
    numbers = None  # line number - 1 of each line kept, when blank lines come before the last one
    if not all(lines):
        numbers = [i for i, line in enumerate(lines) if line]
        lines = [lines[i] for i in numbers]
    if len(lines) > max_samples:
        raise PayloadError(f"payload holds {len(lines)} samples, more than the limit of {max_samples}", status=413)
    if not lines:
        raise PayloadError("empty payload: no samples")
    docs = _lines_at_once(text, lines)
    if docs is None:
        docs = [_line(numbers[k] if numbers else k, line) for k, line in enumerate(lines)]
    return docs, numbers


def _loads(text: str):
    """`json.loads(text)`, through orjson when orjson reads the text (13 us against json's 68 for a message of ten
    samples); else json.loads itself, so that what is accepted and every error stay json's: orjson refuses NaN and
    Infinity (which json reads and the checks refuse by name), numbers beyond a double, lone surrogates, nesting past
    1,024 levels. One difference is left: an integer literal beyond 2^64 comes back from orjson as a float (from json
    as an int); every field refuses such a value either way, the message then writes it as a float."""
    try:
        return orjson.loads(text)
    except orjson.JSONDecodeError:
        return json.loads(text)


def _lines_at_once(text: str, lines: list[str]) -> list[dict] | None:
    """The lines parsed as one JSON array, about 20% faster than line by line (the parser reuses its key strings), or
    None when that is not sure to give each line its own value. It is when the array has as many elements as there are
    lines, every one an object, and no line holds `}`, `,`, `{` in a row (JSON spaces between): then none of the
    array's n - 1 top-level commas lies inside a line, so they are the n - 1 commas put between lines."""
    if _OBJECTS_IN_A_ROW.search(text):
        return None
    try:
        docs = _loads("[" + ",".join(lines) + "]")
    except (ValueError, RecursionError):  # a bad line: each line on its own says which
        return None
    if len(docs) != len(lines) or not all(type(d) is dict for d in docs):
        return None
    return docs


def _line(i: int, line: str):
    try:
        return _loads(line)
    except (ValueError, RecursionError) as e:
        return _BadLine(f"line {i + 1} is not valid JSON ({_json_failure(e)}): {_clip(line)}")


def _json_samples(doc, max_samples: int) -> list:
    if type(doc) is dict:
        return [doc]
    if type(doc) is not list:
        raise PayloadError(
            f"a JSON payload must be an object (one sample) or an array of samples, got {_describe(doc)}"
        )
    if len(doc) > max_samples:
        raise PayloadError(f"payload holds {len(doc)} samples, more than the limit of {max_samples}", status=413)
    if not doc:
        raise PayloadError("empty payload: the array holds no samples")
    return doc


def _json_failure(e: Exception) -> str:
    if isinstance(e, json.JSONDecodeError):
        return f"{e.msg} at column {e.colno}"
    if isinstance(e, RecursionError):
        return "nested too deeply"
    return str(e)


@dataclass(frozen=True)
class _BadLine:
    reason: str


# ------------------------------------------------------------------------------------------------- the samples

_SPEC = {c.name: c for c in TELEMETRY}
_WIRE_KEYS = frozenset(_SPEC)
_REQUIRED = tuple(c.name for c in TELEMETRY if c.required)
_REQUIRED_BUT_ID = frozenset(_REQUIRED) - {"vehicle_id"}
_WIRE_TO_VSS = {s.wire: key for key, s in VSS.items()}
_VIN = "Vehicle.VehicleIdentification.VIN"


def _field_table() -> tuple:
    """(name, is_bool, low, high, required) of every field after vehicle_id and timestamp_ms, in schema order."""
    rows = []
    for c in TELEMETRY:
        if c.name in ("vehicle_id", "timestamp_ms"):
            continue
        if pa.types.is_boolean(c.type):
            rows.append((c.name, True, 0.0, 0.0, c.required))
        elif pa.types.is_floating(c.type):
            rows.append((c.name, False, *RANGES[c.name], c.required))
        else:
            raise TypeError(f"wire.py cannot check telemetry column {c.name} of type {c.type}: teach it")
    return tuple(rows)


_FIELDS = _field_table()
_FIELD = {f[0]: f for f in _FIELDS}
_NUMBERS = tuple((name, low, high, required) for name, is_bool, low, high, required in _FIELDS if not is_bool)
_BOOLS = tuple((name, required) for name, is_bool, _, _, required in _FIELDS if is_bool)
_TEMPLATE = dict.fromkeys(_SPEC)


class _Refused(Exception):
    def __init__(self, field: str | None, reason: str):
        super().__init__(reason)
        self.field = field
        self.reason = reason


class _Checker:
    """Validates one sample at a time against precomputed tables; `check` returns the sample in wire format v1 or raises
    `_Refused` with the first fault. The valid path is one pass of type tests and comparisons; messages are built only
    for faults."""

    def __init__(self, now_ms: int, max_future_ms: int, vehicle_id: str | None):
        self.now_ms = now_ms
        self.max_future_ms = max_future_ms
        self.latest_ms = now_ms + max_future_ms
        self.vehicle_id = vehicle_id
        self.accepted_ids: set[str] = set()  # vehicle ids that passed every check in this payload

    def check(self, doc) -> dict:
        if type(doc) is not dict:
            if type(doc) is _BadLine:
                raise _Refused(None, doc.reason)
            raise _Refused(None, f"sample must be a JSON object, got {_describe(doc)}")
        sample, labels = doc, None
        if doc.keys() != _WIRE_KEYS:  # else every wire field is there: the usual sample
            if not doc.keys() <= _WIRE_KEYS:
                sample, labels = _from_vss(doc)
            if not _REQUIRED_BUT_ID <= sample.keys() or ("vehicle_id" not in sample and self.vehicle_id is None):
                self._missing(sample, labels)

        vid = sample.get("vehicle_id", self.vehicle_id)
        if type(vid) is not str or vid not in self.accepted_ids:
            self._vehicle(vid, labels)
        ts = sample["timestamp_ms"]
        if type(ts) is not int or not 0 <= ts <= self.latest_ms:
            ts = self._timestamp(ts)

        out = _TEMPLATE.copy()  # every wire name in schema order, None until set
        out["vehicle_id"] = vid
        out["timestamp_ms"] = ts
        get = sample.get
        for name, low, high, required in _NUMBERS:
            v = get(name)
            t = type(v)
            if t is float:
                if low <= v <= high:  # False for NaN too
                    out[name] = v
                    continue
            elif t is int:
                if low <= v <= high:
                    out[name] = float(v)
                    continue
            elif v is None and not required:
                continue
            _field_fault(name, v, labels, doc)
        for name, required in _BOOLS:
            v = get(name)
            if v is True or v is False:
                out[name] = v
            elif v is not None or required:
                _field_fault(name, v, labels, doc)
        return out

    def _missing(self, sample: dict, labels: dict | None):
        for name in _REQUIRED:
            if name in sample or (name == "vehicle_id" and self.vehicle_id is not None):
                continue
            if labels is None:
                raise _Refused(name, f"missing required field '{name}'")
            if name == "vehicle_id":
                raise _Refused(_VIN, f"missing required field '{_VIN}' (or 'vehicle_id')")
            if name == "timestamp_ms":
                raise _Refused(
                    name,
                    f"missing required field '{name}' (VSS has no sample time: send timestamp_ms, "
                    "integer ms since the Unix epoch, beside the VSS keys)",
                )
            raise _Refused(_WIRE_TO_VSS[name], f"missing required field '{_WIRE_TO_VSS[name]}'")

    def _vehicle(self, vid, labels: dict | None) -> None:
        label = (labels or {}).get("vehicle_id", "vehicle_id")
        if type(vid) is not str:
            raise _Refused(label, f"{label} must be a string, got {_describe(vid)}")
        if not VEHICLE_ID_RE.fullmatch(vid):
            raise _Refused(label, f"{label} {_quote(vid)} must be 1-64 characters of A-Za-z0-9_.-")
        if self.vehicle_id is not None and vid != self.vehicle_id:
            raise _Refused(label, f"sample of vehicle '{vid}' sent with the credentials of '{self.vehicle_id}'")
        self.accepted_ids.add(vid)

    def _timestamp(self, ts) -> int:
        """The timestamp as an int when it is valid, else _Refused."""
        if type(ts) is float and ts.is_integer():
            ts = int(ts)
        elif type(ts) is float and math.isfinite(ts):
            raise _Refused("timestamp_ms", f"timestamp_ms {ts!r} is not a whole number of milliseconds")
        elif type(ts) is not int:
            raise _Refused(
                "timestamp_ms",
                f"timestamp_ms must be an integer number of milliseconds since the Unix epoch, got {_describe(ts)}",
            )
        if ts < 0:
            raise _Refused("timestamp_ms", f"timestamp_ms {_show(ts)} must be >= 0")
        if ts > self.latest_ms:
            ahead_ms = ts - self.now_ms
            ahead = f"{ahead_ms / 1000:.1f} s" if ahead_ms < 10**18 else "more than 10^15 s"
            raise _Refused(
                "timestamp_ms",
                f"timestamp_ms {_show(ts)} is {ahead} in the future (limit "
                f"{self.max_future_ms / 1000:g} s; server time {self.now_ms})",
            )
        return ts


def _from_vss(doc: dict) -> tuple[dict, dict]:
    """A sample with a key outside wire format v1: (the sample in wire names and units, wire name -> the VSS key sent);
    _Refused for a key that is neither a wire name nor a VSS key (first), or a wire key beside VSS keys."""
    for key in doc:
        if key not in _WIRE_KEYS and key not in VSS:
            raise _Refused(_clip(key), _unknown(key, VSS if key.startswith("Vehicle.") else _WIRE_KEYS))
    sample, labels = {}, {}
    for key, value in doc.items():  # every key is a wire name or a VSS key, and one at least is VSS
        signal = VSS.get(key)
        if signal is not None:
            wire = signal.wire
            labels[wire] = key
            if signal.to_si is not None and type(value) in (int, float):
                try:
                    value = signal.to_si(value)
                except OverflowError:  # an integer beyond float: out of range, the message quotes it as sent
                    value = math.inf
        elif key in VSS_PLAIN_KEYS:
            wire = key
        else:
            raise _Refused(
                key,
                f"wire field '{key}' mixed with VSS keys: a sample is either wire format v1 or VSS "
                f"(only {' and '.join(VSS_PLAIN_KEYS)} may stand beside VSS keys)",
            )
        if wire in sample and sample[wire] != value:  # only vehicle_id beside Vehicle.VehicleIdentification.VIN
            vin, plain = (value, sample[wire]) if key == _VIN else (sample[wire], value)
            raise _Refused(_VIN, f"{_VIN} {_quote(vin)} and vehicle_id {_quote(plain)} differ: send one of them")
        sample[wire] = value
    return sample, labels


def _unknown(key: str, names) -> str:
    if key == "t_s":
        return (
            "unknown field 't_s': the wire format takes timestamp_ms (integer ms since the Unix epoch, UTC), "
            "not t_s, which only files may use"
        )
    close = difflib.get_close_matches(key, names, n=1) if len(key) <= 100 else []
    return f"unknown field '{_clip(key)}'" + (f" (did you mean '{close[0]}'?)" if close else "")


def _field_fault(name: str, value, labels: dict | None, doc: dict):
    """Raise _Refused for a field that failed the valid path, naming the field as the user sent it."""
    _, is_bool, low, high, _ = _FIELD[name]
    label, unit = name, _SPEC[name].unit
    if labels is not None and name in labels:
        label = labels[name]
        value = doc[label]
        signal = VSS[label]
        if signal.from_si is not None:
            low, high = signal.from_si(low), signal.from_si(high)
        unit = signal.unit
    if is_bool:
        raise _Refused(label, f"{label} must be true or false, got {_describe(value)}")
    if type(value) not in (int, float):
        raise _Refused(label, f"{label} must be a number, got {_describe(value)}")
    if type(value) is float and not math.isfinite(value):
        raise _Refused(label, f"{label} must be finite, got {_show(value)}")
    raise _Refused(label, f"{label} {_show(value)} outside [{low:g}, {high:g}] {unit}")


def _identity(doc, vehicle_id: str | None) -> tuple[str | None, int | None]:
    """(vehicle_id, timestamp_ms) of a refused sample, where they can be read."""
    if type(doc) is not dict:
        return None, None
    vid = doc.get("vehicle_id", doc.get(_VIN, vehicle_id))
    if type(vid) is not str or not VEHICLE_ID_RE.fullmatch(vid):
        vid = None
    ts = doc.get("timestamp_ms")
    if type(ts) is float and ts.is_integer():
        ts = int(ts)
    return vid, ts if type(ts) is int and 0 <= ts < 2**63 else None


# ------------------------------------------------------------------------------------------------- Arrow payloads


def arrow_payload(samples: list[dict]) -> bytes:
    """Samples in wire format v1 (dicts with wire names; absent optional fields are null) as an Arrow IPC stream of
    TELEMETRY_SCHEMA, one record batch: what a terminal sends as application/vnd.apache.arrow.stream."""
    table = pa.Table.from_pylist(samples, schema=TELEMETRY_SCHEMA)
    sink = pa.BufferOutputStream()
    with pa.ipc.new_stream(sink, TELEMETRY_SCHEMA) as writer:
        writer.write_table(table)
    return sink.getvalue().to_pybytes()


def is_arrow(body: bytes) -> bool:
    """Whether an MQTT payload (no content type) is an Arrow IPC stream: its first byte is 0xFF, the first of the
    continuation marker that begins every message of the stream format; 0xFF never begins UTF-8 text, so never JSON."""
    return body[:1] == b"\xff"


def _arrow_table(
    body: bytes, max_samples: int, now_ms: int, max_future_ms: int, vehicle_id: str | None
) -> tuple[pa.Table, list[SampleError]]:
    """An Arrow IPC stream of wire format v1 columns: (the valid rows in TELEMETRY_SCHEMA, one SampleError per refused
    row); PayloadError when the stream cannot be read, names a column that is not a wire field, gives a column a type
    that is not its wire type's kind, lacks a required column, or holds no rows or more than `max_samples`. The checks
    run on whole columns (numpy); a message is built for each refused row only."""
    try:
        batches = list(pa.ipc.open_stream(pa.py_buffer(body)))
    except (pa.ArrowException, OSError, ValueError) as e:
        raise PayloadError(f"payload is not an Arrow IPC stream: {_first_line(e)}") from None
    if len(batches) == 1:
        table = batches[0]  # the usual stream: one record batch, its columns used as they are
    else:
        try:
            table = pa.Table.from_batches(batches).combine_chunks()
        except (pa.ArrowException, ValueError):  # no batch at all: the schema only
            raise PayloadError("empty payload: the Arrow stream holds no rows") from None
    names = table.schema.names
    for name in names:
        if name not in _WIRE_KEYS:
            raise PayloadError(f"Arrow payload: {_unknown(name, _WIRE_KEYS)}", field=_clip(name))
    if len(set(names)) != len(names):
        twice = next(n for n in names if names.count(n) > 1)
        raise PayloadError(f"Arrow payload: column '{twice}' appears more than once", field=twice)
    for name in _REQUIRED:
        if name not in names and not (name == "vehicle_id" and vehicle_id is not None):
            raise PayloadError(f"Arrow payload: missing required column '{name}'", field=name)
    if table.num_rows > max_samples:
        raise PayloadError(f"payload holds {table.num_rows} samples, more than the limit of {max_samples}", status=413)
    if table.num_rows == 0:
        raise PayloadError("empty payload: the Arrow stream holds no rows")
    n = table.num_rows
    columns = {}
    for name, column in zip(names, table.columns):
        columns[name] = _arrow_column(name, column)
    if "vehicle_id" not in columns:
        columns["vehicle_id"] = pa.array([vehicle_id] * n, pa.string())

    bad = _arrow_faults(columns, n, now_ms + max_future_ms, vehicle_id)  # (fields in _ARROW_ORDER, rows) or None
    full = pa.table({c.name: columns.get(c.name, pa.nulls(n, c.type)) for c in TELEMETRY}, schema=TELEMETRY_SCHEMA)
    if bad is None:
        return full, []
    faulty = bad.any(axis=0)
    first = bad.argmax(axis=0)  # per row, its first faulty field
    errors = [
        _arrow_error(int(i), _ARROW_ORDER[first[i]], columns, now_ms, max_future_ms, vehicle_id)
        for i in np.flatnonzero(faulty)
    ]
    return full.filter(pa.array(~faulty)), errors


_ARROW_ORDER = ("vehicle_id", "timestamp_ms", *(f[0] for f in _FIELDS))  # the order of the JSON checks
_ARROW_INDEX = {name: k for k, name in enumerate(_ARROW_ORDER)}
_LOW = np.array([low for _, low, _, _ in _NUMBERS])
_HIGH = np.array([high for _, _, high, _ in _NUMBERS])


def _arrow_column(name: str, column: pa.Array | pa.ChunkedArray) -> pa.Array:
    """The column as its wire type: strings, integers and floats of any width, as their kind allows; else
    PayloadError naming the column and both types."""
    want = _SPEC[name].type
    have = column.type
    if pa.types.is_dictionary(have):
        have = have.value_type
    ok = (
        (pa.types.is_string(want) and (pa.types.is_string(have) or pa.types.is_large_string(have)))
        or (pa.types.is_int64(want) and pa.types.is_integer(have))
        or (pa.types.is_floating(want) and (pa.types.is_floating(have) or pa.types.is_integer(have)))
        or (pa.types.is_boolean(want) and pa.types.is_boolean(have))
        or pa.types.is_null(have)
    )
    if not ok:
        raise PayloadError(
            f"Arrow payload: column '{name}' has type {column.type}, the wire format's is {want}", field=name
        )
    if isinstance(column, pa.ChunkedArray):
        column = column.combine_chunks()
    if column.type == want:
        return column
    try:
        return column.cast(want)
    except pa.ArrowInvalid as e:  # an unsigned 64-bit timestamp beyond int64
        raise PayloadError(f"Arrow payload: column '{name}': {_first_line(e)}", field=name) from None


def _arrow_faults(columns: dict, n: int, latest_ms: int, vehicle_id: str | None) -> np.ndarray | None:
    """A boolean array (the fields of _ARROW_ORDER, rows): which field of which row breaks its rule (module
    docstring, "Each sample"), or None when every row is valid. The numbers are checked as one matrix."""
    bad = np.zeros((len(_ARROW_ORDER), n), dtype=bool)
    ids = columns["vehicle_id"]
    values = set(ids.unique().to_pylist())
    wrong = {v for v in values if v is None or not (VEHICLE_ID_RE.fullmatch(v) and v == (vehicle_id or v))}
    if wrong:
        bad[0] = np.isin(ids.fill_null("").to_numpy(zero_copy_only=False), [v or "" for v in wrong])
    ts = columns["timestamp_ms"]
    times = ts.fill_null(-1).to_numpy() if ts.null_count else ts.to_numpy()
    bad[1] = (times < 0) | (times > latest_ms)
    present = [k for k, (name, *_) in enumerate(_NUMBERS) if name in columns]
    if present:
        matrix = np.empty((len(present), n))
        for row, k in enumerate(present):
            matrix[row] = columns[_NUMBERS[k][0]].to_numpy(zero_copy_only=False)  # nulls as NaN
        with np.errstate(invalid="ignore"):
            out = ~((matrix >= _LOW[present, None]) & (matrix <= _HIGH[present, None]))
        for row, k in enumerate(present):
            name, _, _, required = _NUMBERS[k]
            column = columns[name]
            if column.null_count and not required:
                out[row] &= ~column.is_null().to_numpy(zero_copy_only=False)
            bad[_ARROW_INDEX[name]] = out[row]
    for name, required in _BOOLS:
        column = columns.get(name)
        if required and column is not None and column.null_count:
            bad[_ARROW_INDEX[name]] = column.is_null().to_numpy(zero_copy_only=False)
    return bad if bad.any() else None


def _arrow_error(i: int, name: str, columns: dict, now_ms: int, max_future_ms: int, vehicle_id: str | None):
    """The SampleError of row i, whose first fault is in `name`, worded as the JSON checks word it."""
    vid = columns["vehicle_id"][i].as_py()
    ts = columns["timestamp_ms"][i].as_py()
    value = columns[name][i].as_py()
    checker = _Checker(now_ms, max_future_ms, vehicle_id)
    try:
        if value is None:
            raise _Refused(name, f"{name} must not be null: the field is required")
        if name == "vehicle_id":
            checker._vehicle(value, None)
        elif name == "timestamp_ms":
            checker._timestamp(value)
        _field_fault(name, value, None, {})
    except _Refused as e:
        ok_vid = vid if type(vid) is str and VEHICLE_ID_RE.fullmatch(vid) else None
        return SampleError(i, e.field, e.reason, ok_vid, ts if ts is not None and ts >= 0 else None)
    raise AssertionError(f"row {i} refused by the column checks but not by {name}'s")


def _first_line(e: Exception) -> str:
    """The first line of an exception's message (Arrow's run over several), cut to 160 characters."""
    line = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
    return line if len(line) <= 160 else line[:157] + "..."


# ------------------------------------------------------------------------------------------------- messages


def encodable(text: str) -> str:
    """`text` with its lone surrogates (which a JSON \\ud800 escape can carry, and UTF-8, a log or a socket cannot)
    written as \\udXXXX."""
    return text.encode("utf-8", "backslashreplace").decode("utf-8")


def _clip(text: str) -> str:
    """What was sent, quoted in a reason: clipped and encodable."""
    return encodable(text if len(text) <= CLIP_CHARS else text[: CLIP_CHARS - 3] + "...")


def _quote(value) -> str:
    """A string as JSON writes it, clipped: "yes"."""
    return _clip(json.dumps(value, ensure_ascii=False)) if type(value) is str else _describe(value)


def _show(x, fmt: str = "") -> str:
    """A number as the user wrote it, more or less: ints whole (clipped), floats by repr or `fmt`, NaN and Infinity
    as JSON literals."""
    if type(x) is float and not math.isfinite(x):
        return "NaN" if math.isnan(x) else ("Infinity" if x > 0 else "-Infinity")
    if type(x) is float:
        return format(x, fmt) if fmt else repr(x)
    return _clip(str(x))  # json.loads reads at most 4300 digits, which str() can write back


def _describe(value) -> str:
    """A JSON value with its JSON type: string "12", number 3, boolean true, null, array [1, 2], object {...}."""
    if value is None:
        return "null"
    if type(value) is bool:
        return f"boolean {'true' if value else 'false'}"
    if type(value) is str:
        return f"string {_clip(json.dumps(value, ensure_ascii=False))}"
    if type(value) in (int, float):
        return f"number {_show(value)}"
    kind = "array" if type(value) is list else "object"
    try:
        return f"{kind} {_clip(json.dumps(value, ensure_ascii=False, allow_nan=True))}"
    except (ValueError, RecursionError):
        return kind
