"""The `bmw-m8` importer: the real BMW M8 braking log of data/real/bmw_m8_braking (THI CARISSMA with VTI, from the
ROADVIEW project's vehicle-dynamics repository; its README.md describes the columns) turned into wire format v1.

The log is a folder of two CSV files from two loggers: `fast_signals.csv` (about 940 Hz, clock `time`, 0 to 9.6 s:
pedals, steering, reference-sensor velocity, wheel speeds) and `slow_signals.csv` (about 94 Hz, clock `car_time`,
-6.0 to 15.7 s: the car's inertial signals and position). The import, step by step:

1. Clock alignment. The README says the two clocks are the same; the import does not take it on trust but measures
   the offset `offset_s` (`time = car_time + offset_s`) by cross-correlating the longitudinal acceleration
   `Acceleration_X` with the rate of change of the reference speed d(Velocity_X)/dt (`estimate_clock_offset`): two
   measurements of one motion, so the lag of the best Pearson correlation is the clock offset. Both go onto a 5 ms
   grid (bin means of the fast signal, linear interpolation between the slow one's samples), the derivative is
   smoothed over 0.1 s, the same smoothing is applied to the acceleration (so that it adds no lag of its own), lags
   up to +-1 s are tried in 5 ms steps and the peak is refined by a parabola through its neighbours. On synthetic
   logs with a known offset it is right within 1 ms (tests/fleet/test_importers.py). On this log it finds
   offset_s = -5.0 ms, peak correlation 0.9999 (-4.4 to -5.2 ms for grids of 1-5 ms and smoothing over 0.05-0.2 s;
   the launch alone gives -4.9 ms, the braking alone -5.0 ms): half the slow logger's 10 ms period, as if each slow
   sample were stamped at the end of the 10 ms it describes, and within one slow sample of the README's "same
   clock". The import applies the offset it measures; the option `clock_offset_s` sets one instead. (The fast
   signals are themselves interpolated: Velocity_X and the wheel speeds move in straight lines between samples of a
   slower sensor; and `time` stalls once, 11 rows at 7.93968 s, which stays inside one 100 ms bin.)
2. Resampling to 10 Hz without aliasing: each output sample k is the mean of every input sample in its 100 ms bin
   [t_k - 50 ms, t_k + 50 ms) (a box filter, about 94 fast or 9 slow samples each), not a pick of one sample (which
   would fold the ABS's and the road's 10-50 Hz content into the 10 Hz stream). The bins cover the time both loggers
   recorded: t_0 = the later start + 50 ms, on the fast clock; a bin that one logger left empty is dropped.
3. Units and signs to wire v1 (SI, ISO 8855: x forward, y left, z up, positive to the left):

| wire column                | from          | conversion and evidence                                                        |
| -------------------------- | ------------- | ------------------------------------------------------------------------------ |
| speed_mps                  | Velocity_X    | m/s, unchanged (reference sensor, longitudinal)                                |
| wheel_speed_*_radps        | v_wheel_*     | rad/s, unchanged: Velocity_X / v_wheel is 0.345-0.347 m coasting, the tyre's radius (m/s would give 1) |
| accel_lon_mps2             | Acceleration_X| m/s^2, unchanged: positive under throttle, about -12 under full braking       |
| accel_lat_mps2             | Acceleration_Y| m/s^2, unchanged, positive left (see below)                                    |
| yaw_rate_radps             | Yaw_Velocity  | rad/s, unchanged, positive left: d(Yaw)/dt (correlation 0.99, integrals equal), and `Yaw` is the heading of the track Rel_pos_x/y (within 0.07 rad) |
| steering_wheel_angle_rad   | steering      | x `steering_full_scale_rad` (see below)                                        |
| latitude_deg, longitude_deg| Rel_pos_x/y   | metres east/north of `origin` (pymap3d.enu2geodetic); the origin is not in the log |
| lateral_speed_mps          | Velocity_Y    | m/s, unchanged: at the sensor, not the CoG (they differ by yaw rate x the sensor's offset, not given) |
| abs_active                 | -             | false: the log has no ABS signal (see below)                                   |
| acc_active                 | -             | false: a test driver braking by hand                                           |

   Axes: `Pitch` rises to +0.02 rad under braking (nose down) and falls to -0.018 rad under throttle: nose-down
   positive is ISO 8855's pitch (z up, y left); SAE's (z down, y right) has the opposite sign. So the body axes are
   ISO 8855's and `Acceleration_Y`, `Yaw_Velocity` keep their signs; they agree with each other (ay against v r:
   correlation 0.93, slope 1.1 above 5 m/s), and `Yaw`, the integral of Yaw_Velocity, turns counter-clockwise in
   the Rel_pos_x/y plane as the heading of the track does.

   Steering: `steering` is the "normalised steering command" in [-1, 1] of the source's model, which turns it into
   a steering-wheel angle by multiplying with `maximum_steering_angle` (20 rad in its bmw_m8.yaml, marked "Need to be
   checked!") and into a road-wheel angle by dividing by the steering ratio 14.3. So it is the steering wheel, not the
   road wheels, positive left (the source's tyre model turns a positive angle into a force to the left). The log
   bears both out: above 8 m/s (54 samples) the path curvature kappa = yaw rate / speed follows `steering` with
   correlation 0.99 and slope +0.458 1/m per unit, so a positive command turns left, and kinematic steering
   (delta_sw = i_s L kappa) puts the full scale at 14.3 x 2.827 m x 0.458 = 18.5 rad at least; 20 rad leaves an
   understeer term of about 0.45 deg/g at the road wheels, plausible for this car. Default 20 rad
   (`STEERING_FULL_SCALE_RAD`); the option `steering_full_scale_rad` changes it.

   ABS: the log records the brake pedal (0..1) and a brake torque, but no ABS flag or valve signal. The wheel speeds
   do swing under full braking (slip ratios median -3 %, dipping to -15 to -22 % on every wheel at 1.2 g), which
   is what ABS does, but a flag derived from that would be our guess, not the car's: abs_active is false
   throughout, meaning "not reported".

4. Timestamps: `start_ms` + 100 k ms, with `start_ms` an option (default 2024-01-01T00:00:00Z: the log carries no
   date). vehicle_id: an option (default "bmw-m8").

The import is validated with `validate_telemetry` and the M8's wheel radius (the profile bmw_m8.yaml beside this
file, `m8_profile()`), so its unit checks run on it. The table's schema metadata records the clock offset used
(`roadgrip.clock_offset_s`) and how it was found.
"""

from __future__ import annotations

import functools
import logging
import math
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.csv as pacsv
import pymap3d

from roadgrip.data.schema import WHEELS
from roadgrip.data.telemetry import TELEMETRY_SCHEMA, validate_telemetry
from roadgrip.fleet.importers.wire import check_options, check_start_ms, check_vehicle_id, csv_header
from roadgrip.vehicle.params import VehicleParams

logger = logging.getLogger(__name__)

FAST_FILE, SLOW_FILE = "fast_signals.csv", "slow_signals.csv"
FAST_COLUMNS = ("time", "steering", "Velocity_X", "Velocity_Y", *(f"v_wheel_{w}" for w in WHEELS))
SLOW_COLUMNS = ("car_time", "Acceleration_X", "Acceleration_Y", "Yaw_Velocity", "Rel_pos_x", "Rel_pos_y")
PROFILE_PATH = Path(__file__).with_name("bmw_m8.yaml")

PERIOD_S = 0.1  # wire format v1: one sample every 100 ms (CONTRACTS 3.1)
DEFAULT_VEHICLE_ID = "bmw-m8"
DEFAULT_START_MS = 1_704_067_200_000  # 2024-01-01T00:00:00Z: the log has no date, so any fixed epoch will do
# Technische Hochschule Ingolstadt (CARISSMA), Esplanade 10, Ingolstadt, Germany: where the recording team sits; the
# log's positions are relative to an unrecorded origin, so latitude/longitude show the track's shape, not its place.
DEFAULT_ORIGIN = (48.7665, 11.4326)
STEERING_FULL_SCALE_RAD = 20.0  # the source's bmw_m8.yaml `maximum_steering_angle` (see the module docstring)

# Clock alignment (step 1 of the module docstring)
MAX_LAG_S = 1.0
GRID_S = 0.005
SMOOTH_S = 0.1
MIN_CORRELATION = 0.5  # below it the two signals do not show one motion: no offset can be trusted

OPTIONS = (
    "vehicle_id",
    "start_ms",
    "origin_lat_deg",
    "origin_lon_deg",
    "clock_offset_s",
    "max_lag_s",
    "steering_full_scale_rad",
)


@functools.cache
def m8_profile() -> VehicleParams:
    """The BMW M8 of the log as a vehicle profile (CONTRACTS 3.2): bmw_m8.yaml, sources in its comments."""
    return VehicleParams.from_yaml(PROFILE_PATH)


class BmwM8Importer:
    """The BMW M8 log folder (fast_signals.csv and slow_signals.csv; see the module docstring)."""

    name = "bmw-m8"

    def profile(self) -> VehicleParams:
        """The vehicle of the log (optional importer method: `roadgrip fleet --replay` registers it with it)."""
        return m8_profile()

    def detect(self, path: Path) -> bool:
        folder = _folder(Path(path))
        if folder is None:
            return False
        return set(FAST_COLUMNS) <= _header(folder / FAST_FILE) and set(SLOW_COLUMNS) <= _header(folder / SLOW_FILE)

    def load(self, path: Path, **options) -> pa.Table:
        check_options(self.name, options, OPTIONS)
        folder = _folder(Path(path))
        if folder is None:
            raise ValueError(f"{path} is not a BMW M8 log: expected a folder holding {FAST_FILE} and {SLOW_FILE}")
        given = {k: v for k, v in options.items() if v is not None}  # None: the default
        vehicle_id = check_vehicle_id(given.get("vehicle_id", DEFAULT_VEHICLE_ID))
        start_ms = check_start_ms(given.get("start_ms", DEFAULT_START_MS))
        lat0 = _number(options, "origin_lat_deg", DEFAULT_ORIGIN[0], -90.0, 90.0)
        lon0 = _number(options, "origin_lon_deg", DEFAULT_ORIGIN[1], -180.0, 180.0)
        full_scale = _number(options, "steering_full_scale_rad", STEERING_FULL_SCALE_RAD, 0.0, 100.0)
        max_lag_s = _number(options, "max_lag_s", MAX_LAG_S, 0.0, 60.0)

        fast = read_csv_columns(folder / FAST_FILE, FAST_COLUMNS)
        slow = read_csv_columns(folder / SLOW_FILE, SLOW_COLUMNS)
        if options.get("clock_offset_s") is None:
            offset_s, corr = estimate_clock_offset(
                fast["time"], fast["Velocity_X"], slow["car_time"], slow["Acceleration_X"], max_lag_s=max_lag_s
            )
            how = f"cross-correlation of Acceleration_X with d(Velocity_X)/dt, peak correlation {corr:.3f}"
            logger.info("%s: clock offset time - car_time = %.4f s (%s)", folder, offset_s, how)
        else:
            offset_s = _number(options, "clock_offset_s", 0.0, -1e6, 1e6)
            how = "given"
        table = to_wire(
            fast,
            slow,
            offset_s=offset_s,
            vehicle_id=vehicle_id,
            start_ms=start_ms,
            origin=(lat0, lon0),
            steering_full_scale_rad=full_scale,
        )
        batch = validate_telemetry(table, source=str(folder), wheel_radius_m=m8_profile().wheel_radius_m)
        for warning in batch.warnings:
            logger.warning("%s: %s", folder, warning)
        return batch.table.replace_schema_metadata(
            {
                "roadgrip.importer": self.name,
                "roadgrip.clock_offset_s": f"{offset_s:.6f}",
                "roadgrip.clock_offset_method": how,
            }
        )


# ------------------------------------------------------------------------------------------------ reading


def _folder(path: Path) -> Path | None:
    """The log folder of `path` (the folder itself or one of its two files), or None."""
    folder = path.parent if path.is_file() and path.name in (FAST_FILE, SLOW_FILE) else path
    if folder.is_dir() and (folder / FAST_FILE).is_file() and (folder / SLOW_FILE).is_file():
        return folder
    return None


def _header(path: Path) -> set[str]:
    with open(path, encoding="utf-8-sig") as f:
        return csv_header(f.readline())


def read_csv_columns(path: Path, columns: tuple[str, ...]) -> dict[str, np.ndarray]:
    """The float64 `columns` of a CSV file, rows sorted by the first column (stable) with the rows whose first
    column is not a finite number left out."""
    try:
        table = pacsv.read_csv(
            path,
            convert_options=pacsv.ConvertOptions(
                include_columns=list(columns), column_types={c: pa.float64() for c in columns}
            ),
        )
    except (pa.ArrowInvalid, KeyError) as err:
        missing = sorted(set(columns) - _header(path))
        if missing:
            raise ValueError(f"{path} lacks the column(s) {missing} of the BMW M8 log") from None
        raise ValueError(f"cannot read {path}: {err}") from None
    data = {c: table[c].to_numpy(zero_copy_only=False).astype(np.float64) for c in columns}
    t = data[columns[0]]
    order = np.argsort(t, kind="stable")
    order = order[np.isfinite(t[order])]
    if order.size < 2:
        raise ValueError(f"{path} has fewer than two rows with a finite {columns[0]}")
    return {c: v[order] for c, v in data.items()}


def _number(options: dict, name: str, default: float, low: float, high: float) -> float:
    value = options.get(name)
    if value is None:
        return default
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or not (low <= value <= high)
    ):
        raise ValueError(f"{name} must be a number in [{low:g}, {high:g}], got {value!r}")
    return float(value)


# ------------------------------------------------------------------------------------------ clock alignment


def grid_means(t: np.ndarray, x: np.ndarray, start_s: float, period_s: float, n: int) -> np.ndarray:
    """Mean of the samples `x` (at times `t`, s) in each of the `n` bins [start_s + k period_s, start_s + (k+1)
    period_s); NaN for a bin without samples. This is the resampling of step 2 (a box filter, not a pick)."""
    k = np.floor((np.asarray(t, np.float64) - start_s) / period_s).astype(np.int64)
    x = np.asarray(x, np.float64)
    keep = (k >= 0) & (k < n) & np.isfinite(x)
    count = np.bincount(k[keep], minlength=n)[:n]
    total = np.bincount(k[keep], weights=x[keep], minlength=n)[:n]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1), np.nan)


def _on_grid(t: np.ndarray, x: np.ndarray, step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(grid times, values) of the samples `x` (times `t`, sorted) on a uniform grid of `step_s` over their span:
    bin means where the samples are denser than the grid (an anti-aliasing filter), linear interpolation between
    them where they are sparser (a bin mean would move each sample to its bin's centre, up to step_s / 2 off)."""
    t, inverse = np.unique(t, return_inverse=True)
    x = np.bincount(inverse, weights=x) / np.bincount(inverse)  # one value per time: the mean of repeated stamps
    n = int(np.floor((t[-1] - t[0]) / step_s)) + 1
    centres = t[0] + (np.arange(n) + 0.5) * step_s
    if np.median(np.diff(t)) >= step_s:
        return centres, np.interp(centres, t, x)
    means = grid_means(t, x, t[0], step_s, n)
    full = np.isfinite(means)
    return centres, np.interp(centres, centres[full], means[full])


def _smooth(x: np.ndarray, width: int) -> np.ndarray:
    """Centred moving average over `width` samples (odd), the ends averaged over what they have: no lag."""
    width = max(1, width | 1)
    kernel = np.ones(width)
    return np.convolve(x, kernel, "same") / np.convolve(np.ones_like(x), kernel, "same")


def estimate_clock_offset(
    fast_t: np.ndarray,
    speed_mps: np.ndarray,
    slow_t: np.ndarray,
    accel_mps2: np.ndarray,
    *,
    max_lag_s: float = MAX_LAG_S,
    step_s: float = GRID_S,
    smooth_s: float = SMOOTH_S,
) -> tuple[float, float]:
    """(offset_s, peak correlation): the offset between the two clocks, `fast time = slow time + offset_s`, at which
    the slow logger's longitudinal acceleration best matches the rate of change of the fast logger's speed (step 1 of
    the module docstring). Times in s, sorted; `ValueError` when the best correlation is under MIN_CORRELATION (too
    little acceleration in the log to align on) or the peak lies at the edge of +-max_lag_s."""
    if not (max_lag_s > 0 and step_s > 0 and smooth_s >= 0):
        raise ValueError(
            f"max_lag_s, step_s must be > 0 and smooth_s >= 0, got {max_lag_s!r}, {step_s!r}, {smooth_s!r}"
        )
    width = round(smooth_s / step_s)
    tf, v = _on_grid(np.asarray(fast_t, np.float64), speed_mps, step_s)
    dv = _smooth(np.gradient(v, step_s), width)  # d(speed)/dt, m/s^2
    ts, a = _on_grid(np.asarray(slow_t, np.float64), accel_mps2, step_s)
    a = _smooth(a, width)
    k_max = round(max_lag_s / step_s)
    lags = np.arange(-k_max, k_max + 1) * step_s
    corr = np.full(lags.size, np.nan)
    min_overlap = max(10, round(1.0 / step_s))  # at least a second of common record
    overlapped = False
    for i, lag in enumerate(lags):
        shifted = ts + lag  # slow samples on the fast clock for this candidate offset
        inside = (shifted >= tf[0]) & (shifted <= tf[-1])
        if inside.sum() < min_overlap:
            continue
        overlapped = True
        x, y = a[inside], np.interp(shifted[inside], tf, dv)
        x, y = x - x.mean(), y - y.mean()
        denom = math.sqrt(float(np.dot(x, x) * np.dot(y, y)))
        if denom > 0:
            corr[i] = float(np.dot(x, y)) / denom  # Pearson r
    if not np.isfinite(corr).any():
        raise ValueError(
            "cannot align the clocks: "
            + (
                "neither speed nor acceleration varies in the log"
                if overlapped
                else "the two logs overlap by less than a second at every lag tried"
            )
        )
    best = int(np.nanargmax(corr))
    peak = float(corr[best])
    if peak < MIN_CORRELATION:
        raise ValueError(
            f"cannot align the clocks: the best correlation of acceleration with d(speed)/dt is "
            f"{peak:.2f} (at least {MIN_CORRELATION} needed; is there any acceleration in the log?)"
        )
    if best in (0, lags.size - 1) or not np.isfinite(corr[best - 1]) or not np.isfinite(corr[best + 1]):
        raise ValueError(
            f"cannot align the clocks: the best correlation lies at the edge of the lags tried "
            f"(+-{max_lag_s:g} s); try a larger max_lag_s"
        )
    c0, c1, c2 = corr[best - 1], corr[best], corr[best + 1]
    curvature = c0 - 2 * c1 + c2
    shift = 0.5 * (c0 - c2) / curvature if curvature < 0 else 0.0  # vertex of the parabola through the 3 points
    return float(lags[best] + shift * step_s), peak


# ------------------------------------------------------------------------------------------------ to wire


def to_wire(
    fast: dict[str, np.ndarray],
    slow: dict[str, np.ndarray],
    *,
    offset_s: float,
    vehicle_id: str,
    start_ms: int,
    origin: tuple[float, float],
    steering_full_scale_rad: float,
) -> pa.Table:
    """The two logs as wire-format v1 rows (TELEMETRY_SCHEMA, not yet validated): steps 2-4 of the module
    docstring, with the slow clock moved onto the fast one by `offset_s`."""
    t_fast = fast["time"]
    t_slow = slow["car_time"] + offset_s
    start = max(t_fast[0], t_slow[0])
    n = int(np.floor((min(t_fast[-1], t_slow[-1]) - start) / PERIOD_S + 1e-9))
    if n < 1:
        raise ValueError(f"the two logs overlap by less than {PERIOD_S} s after the clock offset {offset_s:.3f} s")
    f = {c: grid_means(t_fast, x, start, PERIOD_S, n) for c, x in fast.items() if c != "time"}
    s = {c: grid_means(t_slow, x, start, PERIOD_S, n) for c, x in slow.items() if c != "car_time"}
    full = np.logical_and.reduce([np.isfinite(x) for x in (*f.values(), *s.values())])
    if not full.all():
        logger.warning("dropped %d of %d 100 ms bins that one of the logs left empty", int((~full).sum()), n)
    k = np.flatnonzero(full)
    lat, lon, _ = pymap3d.enu2geodetic(
        s["Rel_pos_x"][k], s["Rel_pos_y"][k], np.zeros(k.size), origin[0], origin[1], 0.0
    )
    columns = {
        "vehicle_id": pa.array([vehicle_id] * k.size, pa.string()),
        "timestamp_ms": pa.array(start_ms + k * round(PERIOD_S * 1000), pa.int64()),
        "latitude_deg": lat,
        "longitude_deg": lon,
        "speed_mps": f["Velocity_X"][k],
        "accel_lon_mps2": s["Acceleration_X"][k],
        "accel_lat_mps2": s["Acceleration_Y"][k],
        "yaw_rate_radps": s["Yaw_Velocity"][k],
        "steering_wheel_angle_rad": f["steering"][k] * steering_full_scale_rad,
        **{f"wheel_speed_{w}_radps": f[f"v_wheel_{w}"][k] for w in WHEELS},
        "abs_active": np.zeros(k.size, bool),  # not in the log (module docstring)
        "acc_active": np.zeros(k.size, bool),
        "lateral_speed_mps": f["Velocity_Y"][k],
    }
    # optional columns the log has no signal for (tcs_active, esc_active): null, "unknown"
    return pa.table(
        {f.name: columns[f.name] if f.name in columns else pa.nulls(k.size, f.type) for f in TELEMETRY_SCHEMA},
        schema=TELEMETRY_SCHEMA,
    )
