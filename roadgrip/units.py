"""Unit conversions, in one place. Everything else in roadgrip is SI with angles in radians.

A factor `X_PER_Y` is the value in X of one Y: multiply a value in Y by it to get X; divide a value in X by it to get
Y."""

import math

G_MPS2 = 9.80665  # standard gravity (ISO 80000-3)
KMH_PER_MPS = 3.6  # 3600 s per hour / 1000 m per km
MPS_PER_MPH = 0.44704  # the international mile, 1609.344 m, per 3600 s (exact)
MPH_PER_MPS = 1.0 / MPS_PER_MPH
RPM_PER_RADPS = 60.0 / (2.0 * math.pi)  # 60 s per minute / 2 pi rad per revolution
DEG_PER_RAD = 180.0 / math.pi  # also deg/s per rad/s
INCH_M = 0.0254  # the international inch (exact)


def kmh_to_mps(speed_kmh):
    return speed_kmh / KMH_PER_MPS


def mps_to_kmh(speed_mps):
    return speed_mps * KMH_PER_MPS


def deg_to_rad(angle_deg):
    return angle_deg * (math.pi / 180.0)


def rad_to_deg(angle_rad):
    return angle_rad * DEG_PER_RAD


# Units by name, for logs that state theirs (a DBC's signal units, a mapping file): each name's SI unit and the factor
# that takes a value in it to SI (value_si = value x factor). Spellings that loggers and DBC files use for the same unit
# are in UNIT_ALIASES; `canonical_unit` maps them onto these names.
SI_UNITS = {
    "m/s": ("m/s", 1.0),
    "km/h": ("m/s", 1.0 / KMH_PER_MPS),
    "mph": ("m/s", MPS_PER_MPH),
    "m/s^2": ("m/s^2", 1.0),
    "g": ("m/s^2", G_MPS2),
    "rad": ("rad", 1.0),
    "deg": ("rad", math.pi / 180.0),
    "rad/s": ("rad/s", 1.0),
    "deg/s": ("rad/s", math.pi / 180.0),
    "rpm": ("rad/s", 1.0 / RPM_PER_RADPS),
    "m": ("m", 1.0),
    "s": ("s", 1.0),
    "N": ("N", 1.0),
    "kN": ("N", 1000.0),
    "N m": ("N m", 1.0),
}
UNIT_ALIASES = {
    "nm": "N m",
    "n.m": "N m",
    "n*m": "N m",
    "kph": "km/h",
    "kmh": "km/h",
    "km/hr": "km/h",
    "kmph": "km/h",
    "m/s2": "m/s^2",
    "m/s²": "m/s^2",
    "m/s/s": "m/s^2",
    "mps2": "m/s^2",
    "mps": "m/s",
    "degree": "deg",
    "degrees": "deg",
    "°": "deg",
    "deg/sec": "deg/s",
    "degree/s": "deg/s",
    "degrees/s": "deg/s",
    "°/s": "deg/s",
    "radian": "rad",
    "radians": "rad",
    "rad/sec": "rad/s",
    "1/min": "rpm",
    "rev/min": "rpm",
}


def canonical_unit(unit: str) -> str:
    """The name in SI_UNITS of `unit` as a log spells it ('kph' -> 'km/h', 'm/s2' -> 'm/s^2'); case and surrounding
    blanks are ignored. `ValueError` naming it for a unit not known here."""
    key = str(unit).strip()
    if key in SI_UNITS:
        return key
    folded = key.lower()
    for name in SI_UNITS:
        if name.lower() == folded:
            return name
    if folded in UNIT_ALIASES:
        return UNIT_ALIASES[folded]
    raise ValueError(f"unknown unit {unit!r}; known: {sorted(SI_UNITS)} (and the spellings {sorted(UNIT_ALIASES)})")


def to_si(values, unit: str):
    """(values in SI, the SI unit's name) for `values` in `unit` (any spelling `canonical_unit` knows)."""
    si_unit, factor = SI_UNITS[canonical_unit(unit)]
    return values * factor, si_unit
