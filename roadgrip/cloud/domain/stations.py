"""Roadside stations: the road side of vehicle-road coordination (paper 2.1: "intelligent infrastructure on the
roadside" monitors the road state and sends it to the cloud). A road weather station reports what its sensors
measure; the cloud turns each report into friction evidence for the H3 cells the station covers, beside the vehicles'
estimates (the map, roadgrip/cloud/domain/friction_map.py) and as passes of its own in the warning engine
(roadgrip/cloud/domain/warnings.py).

This module owns the report format v1, a station's covered cells and a report's friction evidence (below); the cell
of a position is roadgrip/cloud/domain/cells.py's.

Report format v1 (one JSON object; HTTP may send a JSON array of up to MAX_REPORTS_PER_PAYLOAD of them). SI units,
except the two a road weather station speaks in (degrees Celsius, millimetres), named in the field:

| field | type | unit | rule | DATEX II v3 |
| --- | --- | --- | --- | --- |
| station_id | string | - | 1-64 of `A-Za-z0-9_.-`; the station of the credentials | measurementSiteReference |
| timestamp_ms | integer | ms since Unix epoch, UTC | >= 0, at most max_future_ms ahead of the server | measurementTimeDefault |
| latitude_deg, longitude_deg | number | degrees WGS84 | [-90, 90], [-180, 180]: where the sensors look | pertinentLocation |
| surface_state | string | - | dry, moist, wet, ice, snow or unknown | weatherRelatedRoadConditionType |
| surface_temperature_c | number or null | degC | [-60, 80] | roadSurfaceTemperature |
| water_film_thickness_mm | number or null | mm | [0, 50] | waterFilmThickness (in metres there) |
| friction | number or null | - | [0, 1], as Vaisala DSC111 / Lufft MARWIS report it | friction |
| friction_uncertainty | number or null | - | (0, 0.5]: half-width of the sensor's 90 % interval; only with friction | - |

Unknown fields are errors (with the close name for a typo), as are strings for numbers, NaN and Infinity, values
outside their ranges, a station_id that is not the caller's. A payload is taken whole or not at all: `ReportError`
names the report (index), the field and why.

DATEX II v3 names (checked against the v3 schema as generated into Java in public repositories, see docs/CLOUD.md):
`com:RoadSurfaceConditionMeasurements` holds roadSurfaceTemperature (TemperatureValue), friction (FrictionValue),
waterFilmThickness (FloatingPointMetreDistanceValue: metres), depthOfSnow, iceLayerThickness, icePercentage and the
extension `_roadSurfaceConditionMeasurementsExtension`; the surface state goes beside it in
`roa:RoadSurfaceConditionInformation` as weatherRelatedRoadConditionType (com:WeatherRelatedRoadConditionTypeEnum,
0..n), whose values include dry, moist, wet, ice and snow; "unknown" is written as no value.

Covered cells (`covered_cells`): the station's H3 cell at the map's resolution and every cell whose centre lies within
COVERAGE_RADIUS_M (100 m) of the station: the stretch of road whose surface the station's spot represents (road
weather stations are sited to stand for about that much road either side; a non-invasive sensor itself looks at a
spot a few metres across). At resolution 10 (cell centres ~131 m apart) that is the own cell and, for a station near
a cell's edge, one or two neighbours. Computed by the server from the report's position, never sent.

Friction evidence (`evidence`): (mu, mu_lower, mu_upper), a 90 % interval, all within [0, MU_MAX], or None when the
report says nothing about grip (surface_state unknown and no friction).
1. With a friction reading: friction +- friction_uncertainty (default FRICTION_UNCERTAINTY, 0.1: these optical
   sensors infer grip from the layer they see, water, ice or snow, and its thickness, not from a rolling tire, so we
   trust one reading no more than a class of +-0.1), clipped to [0, MU_MAX].
2. Otherwise from the surface state, `SURFACE_EVIDENCE` (wide on purpose: a state is a class, not a measurement):

   | state | mu | 90 % interval | why |
   | --- | --- | --- | --- |
   | dry | 0.90 | 0.70-1.20 | dry asphalt: 0.8-1.0 in most tables, 1.17 on the Burckhardt dry asphalt (roadgrip/vehicle/tires/burckhardt_surfaces.csv) |
   | moist | 0.70 | 0.50-0.95 | a trace of water: between dry and wet |
   | wet, film <= 0.2 mm | 0.65 | 0.45-0.90 | wet asphalt 0.5-0.8 (Burckhardt 0.80); a thin film drains in the tread |
   | wet, film 0.2-1 mm | 0.55 | 0.35-0.80 | more water than the tread clears at speed |
   | wet, film > 1 mm | 0.45 | 0.20-0.70 | standing water: partial aquaplaning at speed |
   | wet, film unknown | 0.55 | 0.20-0.90 | any of the three |
   | snow | 0.30 | 0.15-0.45 | packed to loose snow 0.2-0.4 (Burckhardt snow 0.19) |
   | ice | 0.12 | 0.05-0.30 | ice 0.05-0.1 (Burckhardt ice 0.05), rough or salted ice up to 0.3 |

3. Ice risk: moist or wet at a surface temperature <= FREEZING_C (0 degC) may be freezing (the de-icer in the water
   sets its freezing point, which the report does not give): the interval widens down to the ice's lower bound and
   mu takes the lower of the two states' (0.12): the report then neither proves grip nor, alone, slipperiness.
"""

from __future__ import annotations

import difflib
import math
from dataclasses import dataclass
from typing import Literal

import h3
from pydantic import BaseModel, ConfigDict, Field, ValidationError, ValidationInfo, field_validator

from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.domain.checks import PayloadError, json_items
from roadgrip.data.telemetry import VEHICLE_ID_RE

SURFACE_STATES = ("dry", "moist", "wet", "ice", "snow", "unknown")
MAX_REPORTS_PER_PAYLOAD = 100
COVERAGE_RADIUS_M = 100.0
FRICTION_UNCERTAINTY = 0.1
MU_MAX = 1.2  # the upper end of every interval: above the Burckhardt dry asphalt's 1.17
FREEZING_C = 0.0
THIN_FILM_MM, THICK_FILM_MM = 0.2, 1.0


@dataclass(frozen=True)
class Evidence:
    mu: float
    mu_lower: float
    mu_upper: float


SURFACE_EVIDENCE = {
    "dry": Evidence(0.90, 0.70, 1.20),
    "moist": Evidence(0.70, 0.50, 0.95),
    "wet_thin": Evidence(0.65, 0.45, 0.90),
    "wet": Evidence(0.55, 0.35, 0.80),
    "wet_thick": Evidence(0.45, 0.20, 0.70),
    "wet_unknown": Evidence(0.55, 0.20, 0.90),
    "snow": Evidence(0.30, 0.15, 0.45),
    "ice": Evidence(0.12, 0.05, 0.30),
}


class StationReport(BaseModel):
    """One report, format v1 (module docstring)."""

    model_config = ConfigDict(extra="forbid", strict=True, frozen=True)

    station_id: str = Field(pattern=VEHICLE_ID_RE.pattern)
    timestamp_ms: int = Field(ge=0)
    latitude_deg: float = Field(ge=-90.0, le=90.0, allow_inf_nan=False)
    longitude_deg: float = Field(ge=-180.0, le=180.0, allow_inf_nan=False)
    surface_state: Literal["dry", "moist", "wet", "ice", "snow", "unknown"]
    surface_temperature_c: float | None = Field(None, ge=-60.0, le=80.0, allow_inf_nan=False)
    water_film_thickness_mm: float | None = Field(None, ge=0.0, le=50.0, allow_inf_nan=False)
    friction: float | None = Field(None, ge=0.0, le=1.0, allow_inf_nan=False)
    friction_uncertainty: float | None = Field(None, gt=0.0, le=0.5, allow_inf_nan=False)

    @field_validator("friction_uncertainty")
    @classmethod
    def _uncertainty_needs_friction(cls, value: float | None, info: ValidationInfo) -> float | None:
        if value is not None and info.data.get("friction") is None:
            raise ValueError("given without friction")
        return value


class ReportError(PayloadError):
    """A payload of station reports refused: `index` (the report in an array; 0 for one object), `field` (None for
    the payload or the report as a whole) and the reason. `status` is the HTTP status to answer."""

    NOUN = "report"


def _field_error(index: int, exc: ValidationError) -> ReportError:
    error = exc.errors()[0]
    field = ".".join(str(p) for p in error["loc"]) or None
    reason = error["msg"].removeprefix("Value error, ")
    if error["type"] == "extra_forbidden":
        close = difflib.get_close_matches(field, StationReport.model_fields, n=1)
        reason = "unknown field" + (f" (did you mean {close[0]!r}?)" if close else "")
    elif "input" in error and error["type"] != "missing":
        reason += f", got {error['input']!r}"[:120]
    return ReportError(reason, index=index, field=field)


def parse_reports(
    body: bytes, *, station_id: str, now_ms: int, max_future_ms: int = 60_000, max_bytes: int = 65_536
) -> list[StationReport]:
    """The reports of an HTTP body or MQTT message (a JSON object, or an array of 1..MAX_REPORTS_PER_PAYLOAD), each
    checked (module docstring) and of `station_id`; ReportError for the first fault, nothing taken then."""
    items = json_items(body, max_bytes=max_bytes, max_items=MAX_REPORTS_PER_PAYLOAD, error=ReportError)
    reports = []
    for index, item in enumerate(items):
        if not isinstance(item, dict):
            raise ReportError(f"a report is a JSON object, got {type(item).__name__}", index=index)
        if isinstance(item.get("timestamp_ms"), float) and item["timestamp_ms"].is_integer():
            item["timestamp_ms"] = int(item["timestamp_ms"])  # 1.7e12: JSON has one number type
        try:
            report = StationReport.model_validate(item)
        except ValidationError as exc:
            raise _field_error(index, exc) from None
        if report.station_id != station_id:
            raise ReportError(
                f"must be the station of the credentials, {station_id!r}, got {report.station_id!r}",
                index=index,
                field="station_id",
            )
        if report.timestamp_ms > now_ms + max_future_ms:
            raise ReportError(
                f"{report.timestamp_ms} is more than {max_future_ms / 1000:g} s ahead of the server's clock ({now_ms})",
                index=index,
                field="timestamp_ms",
            )
        reports.append(report)
    return reports


def covered_cells(
    latitude_deg: float, longitude_deg: float, resolution: int, radius_m: float = COVERAGE_RADIUS_M
) -> list[str]:
    """The station's cell and every cell whose centre lies within radius_m of it, sorted."""
    own = cell_of(latitude_deg, longitude_deg, resolution)
    spacing_m = math.sqrt(3.0) * h3.average_hexagon_edge_length(resolution, "m")  # centre to centre
    k = max(1, math.ceil(radius_m / spacing_m) + 1)
    near = {
        c
        for c in h3.grid_disk(own, k)
        if h3.great_circle_distance((latitude_deg, longitude_deg), h3.cell_to_latlng(c), "m") <= radius_m
    }
    return sorted(near | {own})


def _clip(value: float) -> float:
    return min(MU_MAX, max(0.0, value))


def evidence(report: StationReport) -> Evidence | None:
    """The report's friction evidence, a 90 % interval (module docstring: rules 1-3); None when it says nothing."""
    if report.friction is not None:
        half = FRICTION_UNCERTAINTY if report.friction_uncertainty is None else report.friction_uncertainty
        return Evidence(_clip(report.friction), _clip(report.friction - half), _clip(report.friction + half))
    state = report.surface_state
    if state == "unknown":
        return None
    if state == "wet":
        film = report.water_film_thickness_mm
        state = (
            "wet_unknown"
            if film is None
            else "wet_thin"
            if film <= THIN_FILM_MM
            else "wet"
            if film <= THICK_FILM_MM
            else "wet_thick"
        )
    found = SURFACE_EVIDENCE[state]
    freezing = report.surface_temperature_c is not None and report.surface_temperature_c <= FREEZING_C
    if freezing and report.surface_state in ("moist", "wet"):
        ice = SURFACE_EVIDENCE["ice"]
        return Evidence(min(found.mu, ice.mu), ice.mu_lower, found.mu_upper)
    return found


def evidence_rows(report: StationReport, resolution: int, radius_m: float = COVERAGE_RADIUS_M) -> list[dict]:
    """One row per covered cell for FrictionMap.add_station and WarningEngine.station_evidence: station_id, cell,
    timestamp_ms, mu, mu_lower, mu_upper; none when the report carries no evidence."""
    found = evidence(report)
    if found is None:
        return []
    return [
        {
            "station_id": report.station_id,
            "cell": cell,
            "timestamp_ms": report.timestamp_ms,
            "mu": found.mu,
            "mu_lower": found.mu_lower,
            "mu_upper": found.mu_upper,
        }
        for cell in covered_cells(report.latitude_deg, report.longitude_deg, resolution, radius_m)
    ]


def stored_evidence_rows(stored: dict) -> list[dict]:
    """`evidence_rows` of a stored report (a row of the station_reports table: its evidence's mu, mu_lower, mu_upper,
    null for none, and its covered cells)."""
    if stored["mu"] is None:
        return []
    return [
        {
            "station_id": stored["station_id"],
            "cell": cell,
            "timestamp_ms": stored["timestamp_ms"],
            "mu": stored["mu"],
            "mu_lower": stored["mu_lower"],
            "mu_upper": stored["mu_upper"],
        }
        for cell in stored["cells"]
    ]


def stored_rows(reports: list[StationReport], resolution: int) -> tuple[list[dict], dict[tuple[str, int], list[dict]]]:
    """What storing `reports` takes: the rows for `Storage.put_station_reports` (the report, its evidence's mu,
    mu_lower and mu_upper, null for none, and its covered cells), and each report's `evidence_rows` by its key
    (station_id, timestamp_ms), to hand on those of the reports newly stored."""
    rows, evidence_of = [], {}
    for report in reports:
        found = evidence(report)
        evidence_of[(report.station_id, report.timestamp_ms)] = evidence_rows(report, resolution)
        rows.append(
            {
                **report.model_dump(),
                "mu": None if found is None else found.mu,
                "mu_lower": None if found is None else found.mu_lower,
                "mu_upper": None if found is None else found.mu_upper,
                "cells": covered_cells(report.latitude_deg, report.longitude_deg, resolution),
            }
        )
    return rows, evidence_of
