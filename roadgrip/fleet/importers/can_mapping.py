"""CAN mapping files of the `can-dbc` importer: which message, signal(s) and bus of a car's DBC give each field of wire
format v1, in which unit, with which sign, and the car's vehicle profile. The format is in the docstring of
`roadgrip.fleet.importers.can_dbc`; `load_mapping` reads and checks a file, `check_against_dbc` checks it against a
DBC (messages, signals, units).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import yaml

from roadgrip.data.schema import TELEMETRY
from roadgrip.fleet.importers.wire import check_vehicle_id
from roadgrip.units import SI_UNITS, canonical_unit
from roadgrip.vehicle.params import VehicleParams

MAPPING_KEYS = ("dbc", "vehicle", "vehicle_id", "bus", "max_age_s", "fields")
SOURCE_KEYS = ("message", "signal", "bus", "unit", "sign", "scale", "max_age_s")
DEFAULT_MAX_AGE_S = 0.3  # three periods of the 10 Hz grid: docs/FLEET.md, "Raw CAN logs"
TIME_FIELDS = ("vehicle_id", "timestamp_ms")
BOOL_FIELDS = tuple(c.name for c in TELEMETRY if pa.types.is_boolean(c.type))  # flags: abs_active, acc_active, ...
FIELD_UNITS = {c.name: c.unit for c in TELEMETRY if c.name not in TIME_FIELDS}  # the wire field's own unit
REQUIRED_FIELDS = tuple(c.name for c in TELEMETRY if c.required and c.name not in TIME_FIELDS)
WHEEL_FIELDS = tuple(c.name for c in TELEMETRY if c.name.startswith("wheel_speed_"))


@dataclass(frozen=True)
class SignalSource:
    """Where one wire field comes from: the sum of `signals` (one or more, all in `unit`) of `message` (name or frame
    id) on `bus`, times `sign` (+1 or -1, to turn the car's convention into ISO 8855's) and `scale` (counts to `unit`), converted from `unit` (None
    for a flag: any value but 0 is true) to the field's SI unit. A grid instant needs its latest frame to be no older
    than `max_age_s`."""

    field: str
    message: str | int
    signals: tuple[str, ...]
    bus: int
    unit: str | None
    sign: int
    max_age_s: float
    scale: float = 1.0  # the DBC's value times this is in `unit` (a signal the DBC leaves in counts)

    @property
    def label(self) -> str:
        """How messages name it: field <- MESSAGE.SIGNAL[+SIGNAL] (bus N)."""
        return f"{self.field} <- {self.message}.{'+'.join(self.signals)} (bus {self.bus})"


@dataclass(frozen=True)
class CanMapping:
    """A mapping file, checked (`load_mapping`). `constants` holds the flags the log does not carry (field -> False
    or True); `dbc` is the name of the DBC file it was written for (None: any)."""

    path: Path
    sources: tuple[SignalSource, ...]
    constants: dict[str, bool]
    profile: VehicleParams
    vehicle_id: str | None
    dbc: str | None


def load_mapping(path: str | Path) -> CanMapping:
    """Read and check a mapping file; `ValueError` (`TypeError` for a file or entry that is not a mapping) naming the
    key, field and value at fault."""
    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except (OSError, yaml.YAMLError) as err:
        raise ValueError(f"cannot read the CAN mapping {path}: {err}") from None
    where = f"CAN mapping {path.name}"
    if not isinstance(data, dict):
        raise TypeError(f"{where} must be a mapping of {list(MAPPING_KEYS)}, got {type(data).__name__}")
    _no_unknown(data, MAPPING_KEYS, where)
    if "fields" not in data or not isinstance(data["fields"], dict):
        raise ValueError(f"{where} needs `fields`: a mapping of wire-format fields to their CAN signals")
    if "vehicle" not in data:
        raise ValueError(f"{where} needs `vehicle`: a vehicle profile (CONTRACTS 3.2), a file beside it or inline")
    default_bus = _bus(data.get("bus", 0), f"{where}: bus")
    default_age = _max_age(data.get("max_age_s", DEFAULT_MAX_AGE_S), f"{where}: max_age_s")
    dbc = data.get("dbc")
    if dbc is not None and (not isinstance(dbc, str) or not dbc.lower().endswith(".dbc")):
        raise ValueError(f"{where}: dbc must be the name of a .dbc file, got {dbc!r}")
    vehicle_id = data.get("vehicle_id")
    if vehicle_id is not None:
        check_vehicle_id(vehicle_id)

    sources, constants = [], {}
    for field, spec in data["fields"].items():
        if field not in FIELD_UNITS:
            raise ValueError(f"{where}: {field!r} is not a field of wire format v1; fields: {list(FIELD_UNITS)}")
        if isinstance(spec, bool):
            if field not in BOOL_FIELDS:
                raise ValueError(
                    f"{where}: only the flags {list(BOOL_FIELDS)} may be a constant (not reported), "
                    f"got {field}: {spec!r}"
                )
            constants[field] = spec
            continue
        sources.append(_source(field, spec, default_bus, default_age, where))
    missing = [f for f in REQUIRED_FIELDS if f not in data["fields"]]
    if missing:
        raise ValueError(
            f"{where} lacks the required wire field(s) {missing}; a flag the log lacks is written "
            "`abs_active: false` (not reported)"
        )
    return CanMapping(path, tuple(sources), constants, _profile(data["vehicle"], path, where), vehicle_id, dbc)


def _source(field: str, spec, default_bus: int, default_age: float, where: str) -> SignalSource:
    here = f"{where}: field {field}"
    if not isinstance(spec, dict):
        raise TypeError(f"{here} must be a mapping of {list(SOURCE_KEYS)}, got {spec!r}")
    _no_unknown(spec, SOURCE_KEYS, here)
    message = spec.get("message")
    if isinstance(message, bool) or not isinstance(message, (str, int)) or message == "":
        raise ValueError(f"{here}: message must be a message name or frame id of the DBC, got {message!r}")
    names = spec.get("signal")
    names = [names] if isinstance(names, str) else names
    if not isinstance(names, list) or not names or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"{here}: signal must be a signal name or a list of them (summed), got {spec.get('signal')!r}")
    sign = spec.get("sign", 1)
    if isinstance(sign, bool) or sign not in (1, -1):
        raise ValueError(f"{here}: sign must be 1 or -1, got {sign!r}")
    unit = spec.get("unit")
    if field in BOOL_FIELDS:
        if unit not in (None, "", "-") or len(names) > 1 or sign != 1:
            raise ValueError(f"{here} is a flag: one signal, no unit, no sign (any value but 0 is true), got {spec!r}")
        unit = None
    else:
        if unit is None:
            raise ValueError(f"{here} needs `unit`: the unit the DBC gives {'+'.join(names)} (e.g. km/h, deg/s)")
        unit = _convertible(field, unit, here)
    return SignalSource(
        field,
        message,
        tuple(names),
        _bus(spec.get("bus", default_bus), f"{here}: bus"),
        unit,
        sign,
        _max_age(spec.get("max_age_s", default_age), f"{here}: max_age_s"),
        _scale(spec.get("scale", 1.0), field, here),
    )


def _scale(value, field: str, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{where}: scale must be a number > 0, got {value!r}")
    if field in BOOL_FIELDS and value != 1:
        raise ValueError(f"{where} is a flag: no scale, got {value!r}")
    return float(value)


def _convertible(field: str, unit, where: str) -> str:
    """The canonical name of `unit` if values in it convert to `field`'s unit (wheel speeds: angular, or linear at
    the tyre), else `ValueError`."""
    try:
        name = canonical_unit(unit)
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    target = FIELD_UNITS[field]
    si = SI_UNITS[name][0]
    if field in WHEEL_FIELDS:
        ok = si in ("rad/s", "m/s")
    elif target == "deg":  # latitude and longitude stay in degrees
        ok = name == "deg"
    else:
        ok = si == target
    if not ok:
        raise ValueError(
            f"{where}: unit {unit!r} does not convert to the field's {target}"
            + (" (or a speed at the tyre, divided by the wheel radius)" if field in WHEEL_FIELDS else "")
        )
    return name


def _profile(vehicle, path: Path, where: str) -> VehicleParams:
    if isinstance(vehicle, str):
        file = path.parent / vehicle
        if not file.is_file():
            raise ValueError(f"{where}: vehicle profile {vehicle!r} not found beside it ({file})")
        return VehicleParams.from_yaml(file)
    if isinstance(vehicle, dict):
        return VehicleParams.from_dict(vehicle)
    raise ValueError(f"{where}: vehicle must be a profile file's name or the profile's fields, got {vehicle!r}")


def _no_unknown(data: dict, allowed: tuple[str, ...], where: str) -> None:
    unknown = sorted(map(str, set(data) - set(allowed)))
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {list(allowed)}")


def _bus(value, where: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"{where} must be a bus number >= 0, got {value!r}")
    return value


def _max_age(value, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"{where} must be a number of seconds > 0, got {value!r}")
    return float(value)


# ------------------------------------------------------------------------------------------- against the DBC


def check_against_dbc(mapping: CanMapping, db, dbc_name: str) -> dict[SignalSource, object]:
    """The DBC message of each source, after checking that the message and its signals exist and that every signal's
    unit, where the DBC states one, is the unit the mapping expects; `ValueError` naming the field, message and
    signal otherwise. A signal without a unit in the DBC is taken in the mapping's unit."""
    messages = {}
    for source in mapping.sources:
        here = f"{mapping.path.name}: field {source.field}"
        try:
            message = (
                db.get_message_by_frame_id(source.message)
                if isinstance(source.message, int)
                else db.get_message_by_name(source.message)
            )
        except KeyError:
            raise ValueError(f"{here}: message {source.message!r} is not in {dbc_name}") from None
        known = [s.name for s in message.signals]
        for name in source.signals:
            if name not in known:
                raise ValueError(
                    f"{here}: signal {name!r} is not in message {message.name} of {dbc_name}; its signals: {known}"
                )
            unit = (message.get_signal_by_name(name).unit or "").strip()
            if source.unit is None:
                if unit not in ("", "-"):
                    raise ValueError(
                        f"{here}: signal {message.name}.{name} has unit {unit!r} in {dbc_name}, but "
                        "the field is a flag (no unit)"
                    )
                continue
            if unit in ("", "-"):
                continue
            try:
                same = canonical_unit(unit) == source.unit
            except ValueError:
                same = False
            if not same:
                raise ValueError(
                    f"{here}: signal {message.name}.{name} has unit {unit!r} in {dbc_name}, but the "
                    f"mapping expects {source.unit!r}"
                )
        messages[source] = message
    return messages
