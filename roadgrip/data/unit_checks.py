"""Unit plausibility checks of a telemetry table: is each column in the unit its name says? (`check_units`, called by
`roadgrip.data.telemetry` on the rows that parsed, before the range checks.)

Unit checks compare columns with each other instead of trusting magnitudes, since each signal alone is ambiguous (30 is
a plausible speed in m/s and in km/h). All use medians, percentiles or a least-squares fit over many samples, so a few
bad rows can neither trigger nor mask them; each needs enough moving (or turning) samples and is skipped without them,
never guessed. They run vehicle by vehicle (a fleet's terminals need not agree). The limits were set on the paper preset
and 750 random-preset runs (seeds 3, 5, 7, 11, 13), with and without their wheel radius: none raised a false alarm, and
each wrong unit tested (speed in km/h or mph, wheel speeds in rpm or deg/s, yaw rate in deg/s, steering in degrees,
accel_lon in g) was caught wherever the run had the motion that shows it: for speed and wheel speeds any moving run
given its radius (without one, mph also needs some acceleration or wheels over 0.31 m), for yaw rate and steering a
turning run.

1. speed and wheel speeds. With `wheel_radius_m`: the median of speed / (wheel speed x radius) over moving samples is
   about 1 (0.95-1.09 simulated); each pair of a speed unit (m/s, km/h, mph) and a wheel unit (rad/s, rpm, deg/s) has
   its own ratio (1, 3.6, 2.24, 0.105, 0.0175, 0.377, ...), at least a factor 1.6 from any other, matched within a
   factor `UNIT_TOLERANCE`; a ratio matching none is an error outside [0.5, 2] and a warning (check the radius) inside.
   Without a radius: the implied radius speed / wheel speed must lie in `WHEEL_RADIUS_RANGE_M`, 0.15-0.7 m for any road
   vehicle (0.29-0.43 m simulated); a larger one is a speed in km/h (or mph, when both would fit), a 9.55 or 57.3 times
   smaller one wheel speeds in rpm or deg/s.
2. speed and longitudinal acceleration: the least-squares slope of d(speed)/dt on accel_lon between consecutive samples
   driving straight (|r| < 0.05 rad/s, |ay| < 1.5 m/s^2: in a skid d(vx)/dt = ax + vy r is far from ax) is about 1
   (0.97-1.02 simulated), 3.6 for km/h, 2.24 for mph and 9.81 for an accelerometer in g; used only when the fit gives
   the slope within 10 %, which needs a few m/s^2 of acceleration or braking.
3. last resort for speed, when neither 1 nor 2 could be computed: a 99th percentile above 70 m/s (252 km/h) is km/h.
4. yaw rate: ay = v r in steady driving, so p95(|v r|) / p95(|ay|) over samples above 5 m/s is about 1 in rad/s
   (0.57-6.3 simulated when turning, spins included) and 57 times that in deg/s (32 or more); above `YAW_RATIO_LIMIT`
   (12) means degrees, provided the car turns (p95 |ay| >= 0.5 m/s^2) or |yaw rate| has a 99th percentile above 1.5
   rad/s, which at 5 m/s and more would be a lateral acceleration the accelerometer does not show.
5. steering-wheel angle: delta_sw = i_s (L + K v^2) kappa with kappa = r / v, so the median of |delta_sw| / |kappa| over
   samples with |kappa| >= 0.002 1/m is 37-750 m in rad (the high end: the paper's mu 0.1 circle at full lock) and about
   2300-5000 m in degrees; above `STEER_RATIO_LIMIT` (1500) means degrees. So does a 95th percentile of |angle| beyond
   15 rad, past any steering lock.
   Checks 4 and 5 use the speed: unless check 1 or 2 confirmed its unit, their limits are multiplied by 2.24, the
   largest speed error that can pass check 1 unseen (mph on wheels under 0.31 m).
6. timestamp_ms: a median between 1e9 and 1e10 is seconds since the epoch, above 1e14 micro- or nanoseconds.
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from roadgrip.data.schema import WHEELS
from roadgrip.units import DEG_PER_RAD, G_MPS2, KMH_PER_MPS, MPH_PER_MPS, MPS_PER_MPH, RPM_PER_RADPS

WHEEL_COLUMNS = tuple(f"wheel_speed_{w}_radps" for w in WHEELS)

# The units a column may be in by mistake: value in that unit / value in SI (the factors of roadgrip.units).
SPEED_UNITS = {"m/s": 1.0, "km/h": KMH_PER_MPS, "mph": MPH_PER_MPS}
WHEEL_UNITS = {"rad/s": 1.0, "rpm": RPM_PER_RADPS, "deg/s": DEG_PER_RAD}
ACCEL_UNITS = {"m/s^2": 1.0, "g": 1.0 / G_MPS2}
FIXES = {
    "km/h": f"divide by {KMH_PER_MPS}",
    "mph": f"multiply by {MPS_PER_MPH}",
    "rpm": "multiply by 2 pi / 60",
    "deg/s": "multiply by pi / 180",
    "g": f"multiply by {G_MPS2}",
    "deg": "multiply by pi / 180",
}
SI_UNITS = {
    "speed_mps": "m/s",
    "accel_lon_mps2": "m/s^2",
    "yaw_rate_radps": "rad/s",
    "steering_wheel_angle_rad": "rad",
    "timestamp_ms": "milliseconds",
    **{c: "rad/s" for c in WHEEL_COLUMNS},
}
UNIT_NAMES = {"deg/s": "degrees per second", "deg": "degrees"}

UNIT_TOLERANCE = 1.2  # a ratio matches a unit within this factor; neighbouring units' ratios are >= 1.6 apart
WHEEL_RADIUS_RANGE_M = (0.15, 0.7)  # small city cars to heavy trucks (a 315/80 R22.5 truck tire has 0.54 m)
MIN_SAMPLES = 20  # samples a unit check needs
MOVING_MPS = 5.0  # speed above which yaw rate and steering are compared with lateral motion
MAX_PLAUSIBLE_SPEED_MPS = 70.0  # 252 km/h: a 99th percentile above this is km/h (last resort, see the module doc)
YAW_RATIO_LIMIT = 12.0  # p95(|v r|) / p95(|ay|): 0.57-6.3 simulated in rad/s when turning, x 57 in deg/s
STEER_RATIO_LIMIT = 1500.0  # median |delta_sw| / |kappa| in metres: 37-750 simulated in rad, x 57 in degrees
STEER_MIN_CURVATURE_PER_M = 0.002  # a 500 m radius: below it, sensor bias dominates the steering angle
STEER_LOCK_RAD = 15.0


def check_units(
    values: dict[str, np.ndarray],
    vehicle: np.ndarray,
    ts: np.ndarray,
    ts_raw: np.ndarray,
    time_column: str,
    ok: np.ndarray,
    max_gap_s: float,
    wheel_radius_m: float | None,
) -> tuple[list[str], list[str]]:
    """(errors, warnings) of the unit checks of the module docstring over the rows `ok` that parsed, vehicle by vehicle
    (a fleet's terminals need not agree: one sending km/h among many sending m/s must not hide in a pooled median).

    `values`: column name -> float64 values of every row (file units); `vehicle`: each row's vehicle_id; `ts`: int64
    ms; `ts_raw`: the time column in ms as read, for the check of its unit; `time_column`: timestamp_ms or t_s;
    `max_gap_s`: the longest step between samples that still counts as consecutive; `wheel_radius_m`: the vehicle's,
    if known. Each list is capped at ten messages."""
    errors, warnings = [], []
    if time_column == "timestamp_ms" and ok.any():
        median = float(np.median(ts_raw[ok]))
        unit = (
            "seconds"
            if 1e9 <= median < 1e10
            else "microseconds"
            if 1e14 <= median < 1e17
            else "nanoseconds"
            if median >= 1e17
            else None
        )
        if unit:
            errors.append(
                f"column timestamp_ms looks like {unit} since the epoch, not milliseconds (median "
                f"{median:.4g}, where milliseconds now are about 1.7e12); convert it"
            )
    rows = np.flatnonzero(ok)
    codes = vehicle_codes(vehicle[rows])
    by_vehicle = rows[np.argsort(codes, kind="stable")]
    groups = np.split(by_vehicle, np.flatnonzero(np.diff(np.sort(codes))) + 1) if rows.size else []
    for group in groups:
        if group.size < MIN_SAMPLES:
            continue
        report = _UnitReport()
        v = {k: a[group] for k, a in values.items()}
        speed = _check_speed_and_wheels(v, vehicle[group], ts[group], max_gap_s, wheel_radius_m, report)
        if speed is not None:
            _check_yaw_and_steering(v, *speed, report)
        prefix = f"vehicle {vehicle[group[0]]}: " if len(groups) > 1 else ""
        errors += [prefix + m for m in report.messages()]
        warnings += [prefix + w for w in report.warnings]
    return _capped(errors), _capped(warnings)


def vehicle_codes(ids: np.ndarray) -> np.ndarray:
    """Integer codes of vehicle ids in their lexicographic order."""
    _, inverse = np.unique(ids.astype(str), return_inverse=True)
    return inverse.reshape(-1)


def _capped(messages: list[str], k: int = 10) -> list[str]:
    return messages[:k] + ([f"... and {len(messages) - k} more like these"] if len(messages) > k else [])


def _match(ratio: float, candidates: dict) -> object | None:
    """The key whose expected ratio lies within a factor UNIT_TOLERANCE of `ratio`, else None."""
    for key, expected in candidates.items():
        if ratio > 0 and expected / UNIT_TOLERANCE <= ratio <= expected * UNIT_TOLERANCE:
            return key
    return None


class _UnitReport:
    """Columns found in a wrong unit (one message per unit and evidence), other errors, and warnings."""

    def __init__(self):
        self.found: dict[tuple[str, str], list[str]] = {}  # (unit, evidence) -> columns
        self.errors: list[str] = []
        self.warnings: list[str] = []

    def wrong_unit(self, column: str, unit: str, evidence: str) -> None:
        self.found.setdefault((unit, evidence), []).append(column)

    def messages(self) -> list[str]:
        out = []
        for (unit, evidence), cols in self.found.items():
            subject = f"column {cols[0]} looks" if len(cols) == 1 else f"columns {', '.join(cols)} look"
            out.append(
                f"{subject} like {UNIT_NAMES.get(unit, unit)}, not {SI_UNITS[cols[0]]}: {evidence}; "
                f"convert {'it' if len(cols) == 1 else 'them'} ({FIXES[unit]})"
            )
        return out + self.errors


def _check_speed_and_wheels(v, vehicle, ts, max_gap_s, radius, report: _UnitReport) -> tuple[float, bool] | None:
    """Checks 1-3 of the module docstring. Returns (the factor of the speed column's unit, whether a check confirmed
    it), the factor being 1 when nothing says otherwise; or None when the speed's unit is wrong but cannot be told."""
    speed = v["speed_mps"]
    implied = _implied_radii(speed, v, report)
    speed_unit, evidence, wheel_units = None, "", {}
    if radius is not None:
        speed_unit, evidence, wheel_units = _units_from_radius(implied, radius, report)

    slope = _speed_slope(v, vehicle, ts, max_gap_s)  # 2: d(speed)/dt against accel_lon
    if slope is not None:
        match = _match(slope, {(s, a): fs / fa for s, fs in SPEED_UNITS.items() for a, fa in ACCEL_UNITS.items()})
        if speed_unit is None and match is not None:
            speed_unit = match[0]
            evidence = (
                f"its rate of change is {slope:.3g} times accel_lon_mps2 (least-squares slope; 1 "
                f"expected, {SPEED_UNITS[speed_unit]:.3g} for {speed_unit})"
            )
        elif speed_unit is not None and match is not None and match[0] != speed_unit:
            report.errors.append(
                f"{evidence}, but the rate of change of speed_mps is {slope:.3g} times "
                f"accel_lon_mps2, which says {match[0]}: check wheel_radius_m={radius:g} m and the "
                "units of speed_mps and the wheel speeds"
            )
            return None
        accel_unit = _match(slope / SPEED_UNITS[speed_unit or "m/s"], {u: 1 / f for u, f in ACCEL_UNITS.items()})
        if accel_unit == "g":
            report.wrong_unit(
                "accel_lon_mps2",
                "g",
                f"the rate of change of speed is {slope:.3g} times it "
                f"(least-squares slope; 1 expected, {G_MPS2:.3g} for g)",
            )
        elif accel_unit is None:
            report.warnings.append(
                f"the rate of change of speed_mps is {slope:.3g} times accel_lon_mps2 "
                "(least-squares slope, 1 expected): check the sign and unit of accel_lon_mps2"
            )

    lo, hi = WHEEL_RADIUS_RANGE_M
    confirmed = speed_unit is not None
    if not confirmed and radius is None and implied:  # 1, without a radius: too large an implied radius
        r = float(np.median(list(implied.values())))
        fits = {u: r / SPEED_UNITS[u] for u in ("km/h", "mph") if lo <= r / SPEED_UNITS[u] <= hi}
        text = (
            f"speed_mps / wheel speed implies a wheel radius of {r:.3g} m ({lo}-{hi} m expected; "
            + " or ".join(f"{x:.2g} m if it is {u}" for u, x in fits.items())
            + ")"
        )
        if r > hi and len(fits) == 1:
            speed_unit, evidence, confirmed = next(iter(fits)), text, True
        elif r > hi and fits:
            report.errors.append(f"column speed_mps looks like {' or '.join(fits)}, not m/s: {text}; convert it")
            return None
    if not confirmed and not implied and slope is None:  # 3: the last resort
        p99 = float(np.percentile(np.abs(speed), 99))
        if p99 > MAX_PLAUSIBLE_SPEED_MPS:
            speed_unit = "km/h"
            evidence = (
                f"its 99th percentile is {p99:.4g}, above {MAX_PLAUSIBLE_SPEED_MPS:g} m/s "
                f"({MAX_PLAUSIBLE_SPEED_MPS * KMH_PER_MPS:.0f} km/h), and neither wheel speeds nor "
                "accelerations could be compared with it"
            )
    if speed_unit not in (None, "m/s"):
        report.wrong_unit("speed_mps", speed_unit, evidence)
    speed_factor = SPEED_UNITS[speed_unit or "m/s"]

    found: dict[str, dict[str, float]] = {}  # the wheels' units, given the speed's: unit -> {column: ratio}
    unexplained = {}
    for col, r in implied.items():
        if radius is not None:
            unit = wheel_units.get(col)
            if unit is not None and unit[0] == (speed_unit or "m/s") and unit[1] != "rad/s":
                found.setdefault(unit[1], {})[col] = r / radius
            continue
        r = r / speed_factor
        if not lo <= r <= hi:
            unit = next((u for u, f in WHEEL_UNITS.items() if lo <= r * f <= hi), None)
            if unit is None:
                unexplained[col] = r
            else:
                found.setdefault(unit, {})[col] = r
    for unit, ratios in found.items():
        x = float(np.median(list(ratios.values())))
        if radius is not None:
            evidence = (
                f"speed_mps / (wheel speed x wheel_radius_m) over moving samples is {x:.3g} (1 expected; "
                f"{speed_factor / WHEEL_UNITS[unit]:.3g} for {unit})"
            )
        else:
            evidence = (
                f"speed / wheel speed implies a wheel radius of {x:.2g} m ({lo}-{hi} m expected; "
                f"{x * WHEEL_UNITS[unit]:.2g} m for {unit}{'' if confirmed else ', if speed_mps is m/s'})"
            )
        for col in ratios:
            report.wrong_unit(col, unit, evidence)
    if unexplained:
        r = float(np.median(list(unexplained.values()))) * speed_factor
        combos = [
            f"speed in {s} with wheel speeds in {w}"
            for s, fs in SPEED_UNITS.items()
            for w, fw in WHEEL_UNITS.items()
            if (s, w) != ("m/s", "rad/s") and lo <= r * fw / fs <= hi and (not confirmed or s == (speed_unit or "m/s"))
        ]
        report.errors.append(
            f"speed_mps / wheel speed implies a wheel radius of {r:.3g} m ({lo}-{hi} m expected for a road vehicle) "
            f"for {', '.join(unexplained)}: check the units of speed_mps and the wheel speeds"
            + (f" ({' or '.join(combos)} would explain it)" if combos else "")
        )
        if not confirmed:
            return None  # the speed itself may be wrong: leave the checks that use it alone
    return speed_factor, confirmed


def _moving_threshold(x: np.ndarray) -> float:
    """|x| above which a sample counts as moving: a fifth of the 95th percentile, the same samples whatever the unit
    (the slowest samples are where sensors misbehave: wheel-speed drop-out, quantisation, creeping at a stop), and at
    least 1 in the file's unit, so that a parked car's noise is never taken for motion."""
    return max(0.2 * float(np.percentile(np.abs(x), 95)), 1.0)


def _implied_radii(speed: np.ndarray, v: dict, report: _UnitReport) -> dict[str, float]:
    """Per wheel column, the median of speed / wheel speed over samples where both clearly move (file units)."""
    implied = {}
    for col in WHEEL_COLUMNS:
        w = v[col]
        moving = (
            (np.abs(speed) >= _moving_threshold(speed))
            & (np.abs(w) >= _moving_threshold(w))
            & (np.sign(speed) == np.sign(w))
        )
        if moving.sum() >= MIN_SAMPLES:
            implied[col] = float(np.median(speed[moving] / w[moving]))
    unchecked = [c for c in WHEEL_COLUMNS if c not in implied]
    if unchecked:
        report.warnings.append(
            f"too few moving samples to compare {', '.join(unchecked)} with speed_mps (units not verified)"
        )
    return implied


def _units_from_radius(implied: dict[str, float], radius: float, report: _UnitReport):
    """Check 1 with a radius: (speed unit or None, its evidence, wheel column -> (speed unit, wheel unit) or None)."""
    pairs = {(s, w): fs / fw for s, fs in SPEED_UNITS.items() for w, fw in WHEEL_UNITS.items()}
    units = {}
    for col, r in implied.items():
        q = r / radius
        units[col] = _match(q, pairs)
        if units[col] is None:
            text = f"speed_mps / ({col} x wheel_radius_m) over moving samples has median {q:.3g}, about 1 expected"
            if 0.5 <= q <= 2.0:
                report.warnings.append(f"{text}: check wheel_radius_m={radius:g} m")
            else:
                report.errors.append(
                    f"{text}, and no unit of speed (m/s, km/h, mph) and wheel speed (rad/s, rpm, "
                    f"deg/s) explains it: check these columns and wheel_radius_m={radius:g} m"
                )
    votes = Counter(u for u in units.values() if u is not None).most_common(1)
    if not votes or votes[0][1] < len(implied) // 2 + 1:
        return None, "", units
    pair = votes[0][0]
    q = float(np.median([implied[c] / radius for c, u in units.items() if u == pair]))
    return (
        pair[0],
        (
            f"speed_mps / (wheel speed x wheel_radius_m) over moving samples is {q:.3g} (1 expected; "
            f"{pairs[pair]:.3g} for speed in {pair[0]}, wheel speeds in {pair[1]})"
        ),
        units,
    )


def _check_yaw_and_steering(v, speed_factor: float, confirmed: bool, report: _UnitReport) -> None:
    """Checks 4 and 5 of the module docstring. Both use the speed; unless a check confirmed its unit, their limits are
    raised by the largest error that can pass unnoticed (mph read as m/s: with wheels under 0.31 m, the implied radius
    stays plausible)."""
    margin = 1.0 if confirmed else MPH_PER_MPS
    sw95 = float(np.percentile(np.abs(v["steering_wheel_angle_rad"]), 95))
    v_mps = v["speed_mps"] / speed_factor
    moving = v_mps > MOVING_MPS
    steer_evidence = None
    if moving.sum() >= MIN_SAMPLES:
        r, ay, speed = v["yaw_rate_radps"][moving], v["accel_lat_mps2"][moving], v_mps[moving]
        ay95 = float(np.percentile(np.abs(ay), 95))
        vr95 = float(np.percentile(np.abs(speed * r), 95))
        r99 = float(np.percentile(np.abs(r), 99))
        yaw_factor = 1.0
        if ay95 > 0 and vr95 / ay95 > YAW_RATIO_LIMIT * margin and (ay95 >= 0.5 or r99 > 1.5):
            yaw_factor = DEG_PER_RAD
            report.wrong_unit(
                "yaw_rate_radps",
                "deg/s",
                f"speed x yaw rate is {vr95 / ay95:.3g} times the lateral acceleration (95th percentiles "
                f"above {MOVING_MPS:g} m/s; about 1 expected, as ay = v r; 99th percentile of |yaw rate| "
                f"{r99:.3g})",
            )
        kappa = r / yaw_factor / speed  # path curvature, 1/m
        curving = np.abs(kappa) >= STEER_MIN_CURVATURE_PER_M
        if curving.sum() >= MIN_SAMPLES:
            ratio = float(np.median(np.abs(v["steering_wheel_angle_rad"][moving][curving]) / np.abs(kappa[curving])))
            if ratio > STEER_RATIO_LIMIT * margin:
                steer_evidence = (
                    f"the median of |angle| / path curvature (yaw rate / speed) is {ratio:.4g} m "
                    "(steering ratio x wheelbase, more when understeering: 37-750 m in rad)"
                )
    if steer_evidence is None and sw95 > STEER_LOCK_RAD:
        steer_evidence = f"its 95th percentile of |angle| is {sw95:.4g}, past any steering lock (about 15 rad)"
    if steer_evidence:
        report.wrong_unit("steering_wheel_angle_rad", "deg", steer_evidence)


def _speed_slope(v: dict, vehicle, ts, max_gap_s) -> float | None:
    """Least-squares slope of d(speed)/dt on accel_lon between consecutive samples of a vehicle that move (see
    `_moving_threshold`) straight, or None unless it is positive and known within 10 % (enough samples and enough
    acceleration).

    In the body frame d(vx)/dt = ax + vy r: the samples keep |r| < 0.05 rad/s and |ay| < 1.5 m/s^2 at both ends, where
    vy r is negligible (in a skid it is not: a spinning car's vx falls at several g with ax near zero)."""
    order = np.lexsort((ts, vehicle_codes(vehicle)))
    s, a, t, veh = v["speed_mps"][order], v["accel_lon_mps2"][order], ts[order], vehicle[order]
    straight = (np.abs(v["yaw_rate_radps"][order]) < 0.05) & (np.abs(v["accel_lat_mps2"][order]) < 1.5)
    dt = np.diff(t) / 1000.0
    fast = np.abs(s) >= _moving_threshold(s)
    moving = fast[1:] & fast[:-1]
    pair = (veh[1:] == veh[:-1]) & (dt > 0) & (dt <= max_gap_s) & moving & straight[1:] & straight[:-1]
    if pair.sum() < 30:
        return None
    x = 0.5 * (a[1:] + a[:-1])[pair]
    y = np.diff(s)[pair] / dt[pair]
    xc, yc = x - x.mean(), y - y.mean()
    sxx = float(np.sum(xc * xc))
    if sxx <= 0:
        return None
    slope = float(np.sum(xc * yc) / sxx)  # b = Sxy / Sxx
    se = math.sqrt(float(np.sum((yc - slope * xc) ** 2)) / (x.size - 2) / sxx)  # se(b) = sqrt(s^2 / Sxx)
    return slope if slope > 0 and se < 0.1 * slope else None
