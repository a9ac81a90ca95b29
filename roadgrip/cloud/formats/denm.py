"""Slippery-road warnings (WarningEvent, roadgrip/cloud/domain/warnings.py) as ETSI DENMs. A pure function; no I/O.

DENM: a JSON rendering of an ETSI EN 302 637-3 (v1.3.1) DENM, protocol version 2, field names and order as in its ASN.1
(DENM-PDU-Descriptions, ITS-Container v2): ENUMERATED values as their identifiers ("isCancellation", "lessThan100m"),
INTEGER values as numbers. Choices:
- actionID.sequenceNumber is the warning's own number (WarningEvent.action_sequence_number), the same in the new DENM,
  its updates and its cancellation: that is how receivers tie an update or a cancellation to the event. The count of
  updates (WarningEvent.sequence_number) is ours and goes in the "roadgrip" block.
- detectionTime is WarningEvent.evidence_ms: for a new DENM the detection; for an update the low-friction pass that
  refreshed it; for a cancellation the dry pass that ended it (or the expiry instant), as EN 302 637-3 asks ("for the
  DENM update, the time at which the event update is detected"). referenceTime is WarningEvent.updated_ms, when this
  DENM was generated. validityDuration counts from detectionTime, so the warning lapses at the same instant for a
  receiver as in the engine (last low pass + validity_s).
- TimestampIts: ITS time counts TAI milliseconds since 2004-01-01T00:00:00.000 UTC, so it runs ahead of Unix time by
  the leap seconds inserted since 2004: five, at the ends of 2005-12, 2008-12, 2012-06, 2015-06 and 2016-12 (IERS
  Bulletin C; none announced since, up to 2026). `timestamp_its_ms` adds each from the instant it took effect; a leap
  second announced later must be added to LEAP_SECONDS_UNIX_S.
- eventPosition: the cell centre in 0.1 microdegree (1e-7 degree) integers; the confidence ellipse is a circle of the
  cell's circumradius (the farthest boundary vertex from the centre) in centimetres, outOfRange (4094) when over 4093 cm
  as it is at resolution 10 (about 76 m); altitude unavailable.
- relevanceDistance: the smallest RelevanceDistance class that holds the cell's circumradius (lessThan100m at
  resolution 10).
- informationQuality (1..7; 0 would be "unavailable"): min(7, n_passes + 2 (n_vehicles - 1)). Independent vehicles count
  double because a vehicle's passes share its estimator's bias, tires and vehicle profile: two passes of one vehicle
  give 2, one pass each of two vehicles 4, three vehicles 7.
- eventType: causeCode 6 adverseWeatherCondition-Adhesion, subCauseCode 0 (unavailable): low mu does not tell ice
  from snow, oil or frost.
- stationType 15 (roadSideUnit): the cloud speaks through roadside units.
- A top-level "roadgrip" block (not part of the DENM) carries the cell, warning id, status, reason, the evidence
  (mu_upper, passes, vehicles) and the update count.

UPER: the same message as C-ITS stations exchange it, `denm_uper(denm(event))`: the JSON rendering's "header" and
"denm" members are the ASN.1 value of the type DENM as asn1tools takes it, encoded with the unaligned packed encoding
rules (46 bytes at resolution 10, docs/CONTRACTS.md) against the ETSI modules shipped in asn1/ (EN 302 637-3 v1.3.1
DENM-PDU-Descriptions, TS 102 894-2 v1.3.1 ITS-Container; asn1/README.md), compiled once per process. Constraints are checked on encoding: a value
outside its ASN.1 range is a ValueError, never a wrong byte. `decode_denm_uper` reads one back. The "roadgrip" block
has no place in the DENM and is not encoded. Several DENMs in one body (GET /v1/warnings/uper) are framed: each is
preceded by its length in bytes as a 4-byte unsigned big-endian integer (`frame`, `unframe`).
"""

from __future__ import annotations

import bisect
import functools
import math
import struct
from pathlib import Path

import asn1tools
import h3

from roadgrip.cloud.domain.warnings import MAX_VALIDITY_S, WarningEvent

ASN1_DIR = Path(__file__).with_name("asn1")  # the ETSI ASN.1 modules (asn1/README.md)
DENM_MEMBERS = ("header", "denm")  # the members of denm()'s JSON that are the ASN.1 DENM
FRAME_LENGTH = struct.Struct(">I")  # the length before each DENM of a framed body

ITS_EPOCH_UNIX_MS = 1_072_915_200_000  # 2004-01-01T00:00:00Z in Unix ms (UTC)
# Unix time (s) from which each leap second since 2004 counts: 2006-01-01, 2009-01-01, 2012-07-01, 2015-07-01, 2017-01-01
LEAP_SECONDS_UNIX_S = (1_136_073_600, 1_230_768_000, 1_341_100_800, 1_435_708_800, 1_483_228_800)

DENM_PROTOCOL_VERSION = 2
DENM_MESSAGE_ID = 1  # ItsPduHeader messageID denm(1)
CAUSE_ADVERSE_WEATHER_ADHESION = 6  # CauseCodeType adverseWeatherCondition-Adhesion
SUB_CAUSE_UNAVAILABLE = 0
STATION_TYPE_ROAD_SIDE_UNIT = 15
LATITUDE_UNAVAILABLE = 900_000_001
ALTITUDE_UNAVAILABLE = 800_001
SEMI_AXIS_OUT_OF_RANGE = 4094  # SemiAxisLength: cm, 4094 outOfRange
# RelevanceDistance: (upper bound in m, identifier); beyond the last: over10km
RELEVANCE_DISTANCES = (
    (50.0, "lessThan50m"),
    (100.0, "lessThan100m"),
    (200.0, "lessThan200m"),
    (500.0, "lessThan500m"),
    (1000.0, "lessThan1000m"),
    (5000.0, "lessThan5km"),
    (10000.0, "lessThan10km"),
)


def timestamp_its_ms(unix_ms: int) -> int:
    """ETSI TimestampIts: ms since 2004-01-01T00:00:00.000 UTC, counting the leap seconds since (TAI-like)."""
    unix_ms = int(unix_ms)
    if unix_ms < ITS_EPOCH_UNIX_MS:
        raise ValueError(f"unix_ms must be at or after 2004-01-01T00:00:00Z ({ITS_EPOCH_UNIX_MS}), got {unix_ms}")
    leap_seconds = bisect.bisect_right(LEAP_SECONDS_UNIX_S, unix_ms // 1000)
    return unix_ms - ITS_EPOCH_UNIX_MS + 1000 * leap_seconds


def cell_radius_m(cell: str) -> float:
    """Circumradius of an H3 cell: the farthest boundary vertex from its centre, in metres."""
    centre = h3.cell_to_latlng(cell)
    return max(h3.great_circle_distance(centre, vertex, unit="m") for vertex in h3.cell_to_boundary(cell))


def relevance_distance(radius_m: float) -> str:
    for bound_m, name in RELEVANCE_DISTANCES:
        if radius_m < bound_m:
            return name
    return "over10km"


def information_quality(n_passes: int, n_vehicles: int) -> int:
    """InformationQuality 1..7 from the evidence: min(7, n_passes + 2 (n_vehicles - 1)), at least 1."""
    return max(1, min(7, n_passes + 2 * (max(n_vehicles, 1) - 1)))


def denm(event: WarningEvent, station_id: int | None = None) -> dict:
    """The DENM (EN 302 637-3, protocol version 2) of a warning event as JSON-able dict; see the module docstring.
    station_id defaults to the event's (the engine's) station."""
    station = event.station_id if station_id is None else int(station_id)
    radius_m = cell_radius_m(event.cell)
    semi_axis_cm = min(SEMI_AXIS_OUT_OF_RANGE, math.ceil(radius_m * 100.0))
    validity = math.ceil(event.validity_s)
    if not 0 <= validity <= MAX_VALIDITY_S:
        raise ValueError(f"validity_s must be within 0..{MAX_VALIDITY_S} s for a DENM, got {event.validity_s!r}")
    management = {
        "actionID": {"originatingStationID": station, "sequenceNumber": event.action_sequence_number},
        "detectionTime": timestamp_its_ms(event.evidence_ms),
        "referenceTime": timestamp_its_ms(event.updated_ms),
    }
    if event.status == "cancelled":
        management["termination"] = "isCancellation"
    management.update(
        {
            "eventPosition": {
                "latitude": round(event.latitude_deg * 1e7),  # Latitude: 0.1 microdegree
                "longitude": round(event.longitude_deg * 1e7),
                "positionConfidenceEllipse": {
                    "semiMajorConfidence": semi_axis_cm,
                    "semiMinorConfidence": semi_axis_cm,
                    "semiMajorOrientation": 0,
                },  # a circle: orientation wgs84North
                "altitude": {"altitudeValue": ALTITUDE_UNAVAILABLE, "altitudeConfidence": "unavailable"},
            },
            "relevanceDistance": relevance_distance(radius_m),
            "relevanceTrafficDirection": "allTrafficDirections",
            "validityDuration": validity,
            "stationType": STATION_TYPE_ROAD_SIDE_UNIT,
        }
    )
    return {
        "header": {"protocolVersion": DENM_PROTOCOL_VERSION, "messageID": DENM_MESSAGE_ID, "stationID": station},
        "denm": {
            "management": management,
            "situation": {
                "informationQuality": information_quality(event.n_passes, event.n_vehicles),
                "eventType": {"causeCode": CAUSE_ADVERSE_WEATHER_ADHESION, "subCauseCode": SUB_CAUSE_UNAVAILABLE},
            },
        },
        "roadgrip": {
            "cell": event.cell,
            "warning_id": event.warning_id,
            "status": event.status,
            "reason": event.reason,
            "mu_upper": event.mu_upper,
            "n_passes": event.n_passes,
            "n_vehicles": event.n_vehicles,
            "update": event.sequence_number,
        },
    }


@functools.cache
def _uper() -> asn1tools.compiler.Specification:
    """The ETSI modules in asn1/ compiled for UPER (once per process: about 0.2 s)."""
    return asn1tools.compile_files(sorted(str(path) for path in ASN1_DIR.glob("*.asn")), "uper")


def denm_uper(message: dict) -> bytes:
    """The UPER encoding of a DENM rendered by `denm` (its "header" and "denm" members; the "roadgrip" block is not
    part of the DENM). A member missing or a value outside its ASN.1 type is a ValueError naming it."""
    missing = [name for name in DENM_MEMBERS if name not in message]
    if missing:
        raise ValueError(f"a DENM needs the members {DENM_MEMBERS}, missing {missing}")
    try:
        return _uper().encode("DENM", {name: message[name] for name in DENM_MEMBERS}, check_constraints=True)
    except asn1tools.Error as exc:
        raise ValueError(f"DENM does not fit the ETSI ASN.1: {exc}") from None


def decode_denm_uper(data: bytes) -> dict:
    """A UPER-encoded DENM as the ASN.1 value (the "header" and "denm" members of `denm`'s JSON); malformed bytes are a
    ValueError."""
    try:
        return _uper().decode("DENM", bytes(data), check_constraints=True)
    except asn1tools.Error as exc:
        raise ValueError(f"not a UPER-encoded DENM ({len(data)} bytes): {exc}") from None


def frame(messages: list[bytes]) -> bytes:
    """Encoded DENMs in one body, each preceded by its length (a 4-byte unsigned big-endian integer)."""
    return b"".join(FRAME_LENGTH.pack(len(m)) + m for m in messages)


def unframe(body: bytes) -> list[bytes]:
    """The DENMs of a framed body (`frame`); a truncated body is a ValueError naming the offset."""
    messages, offset = [], 0
    while offset < len(body):
        if offset + FRAME_LENGTH.size > len(body):
            raise ValueError(f"framed DENMs: a length cut short at byte {offset} of {len(body)}")
        (size,) = FRAME_LENGTH.unpack_from(body, offset)
        offset += FRAME_LENGTH.size
        if offset + size > len(body):
            raise ValueError(f"framed DENMs: a {size}-byte DENM at byte {offset} overruns the {len(body)}-byte body")
        messages.append(bytes(body[offset : offset + size]))
        offset += size
    return messages
