"""The one source of truth for column names, types and units: telemetry wire format v1 (CONTRACTS 3.1), the simulation
dataset (CONTRACTS 3.3) and the estimate (CONTRACTS 3.4) as the cloud stores and publishes it."""

from __future__ import annotations

from dataclasses import dataclass

import pyarrow as pa

WIRE_FORMAT_VERSION = 1
WHEELS = ("fl", "fr", "rl", "rr")


@dataclass(frozen=True)
class Column:
    name: str
    type: pa.DataType
    unit: str
    description: str
    required: bool = True


OPTIONAL_CHANNELS = (
    Column(
        "gnss_speed_mps",
        pa.float64(),
        "m/s",
        "speed over ground from GNSS Doppler, not fused with the wheel speeds",
        required=False,
    ),
    Column(
        "gnss_speed_accuracy_mps",
        pa.float64(),
        "m/s",
        "the GNSS receiver's own 1-sigma speed accuracy (u-blox sAcc)",
        required=False,
    ),
    Column(
        "drive_force_n",
        pa.float64(),
        "N",
        "longitudinal force the powertrain applies at the wheels, all driven wheels together",
        required=False,
    ),
    Column(
        "brake_force_n",
        pa.float64(),
        "N",
        "force of the friction brakes at the wheels, all together, >= 0",
        required=False,
    ),
    Column(
        "steering_torque_nm",
        pa.float64(),
        "N m",
        "the driver's torque on the steering wheel, positive left",
        required=False,
    ),
    Column(
        "eps_assist_torque_nm",
        pa.float64(),
        "N m",
        "the power steering motor's assist referred to the column, positive left",
        required=False,
    ),
)
CHANNEL_NAMES = tuple(c.name for c in OPTIONAL_CHANNELS)

TELEMETRY = (
    Column("vehicle_id", pa.string(), "-", "1-64 characters of A-Za-z0-9_.-"),
    Column("timestamp_ms", pa.int64(), "ms", "milliseconds since the Unix epoch, UTC"),
    Column("latitude_deg", pa.float64(), "deg", "WGS84 latitude", required=False),
    Column("longitude_deg", pa.float64(), "deg", "WGS84 longitude", required=False),
    Column("speed_mps", pa.float64(), "m/s", "vehicle speed as the terminal reports it"),
    Column("accel_lon_mps2", pa.float64(), "m/s^2", "longitudinal body acceleration"),
    Column("accel_lat_mps2", pa.float64(), "m/s^2", "lateral body acceleration, positive left"),
    Column("yaw_rate_radps", pa.float64(), "rad/s", "yaw rate, positive left"),
    Column("steering_wheel_angle_rad", pa.float64(), "rad", "steering-wheel angle, positive left"),
    *(Column(f"wheel_speed_{w}_radps", pa.float64(), "rad/s", f"wheel angular speed, {w}") for w in WHEELS),
    Column("abs_active", pa.bool_(), "-", "ABS intervening"),
    Column("acc_active", pa.bool_(), "-", "adaptive cruise control engaged"),
    Column(
        "tcs_active", pa.bool_(), "-", "traction control intervening (absent: unknown, taken as false)", required=False
    ),
    Column(
        "esc_active", pa.bool_(), "-", "stability control intervening (absent: unknown, taken as false)", required=False
    ),
    Column(
        "lateral_speed_mps",
        pa.float64(),
        "m/s",
        "lateral speed of the CoG (simulations, some test vehicles)",
        required=False,
    ),
    # Optional channels many production cars have (CONTRACTS 3.1): absent (null, NaN) means "not sent", never zero
    *OPTIONAL_CHANNELS,
)

GROUND_TRUTH = (
    Column("run_id", pa.string(), "-", "run identifier"),
    Column("condition", pa.string(), "-", "road condition label (paper: low, medium, high, increasing, decreasing)"),
    Column("road", pa.string(), "-", "road geometry label (paper: straight, circular)"),
    Column("manoeuvre", pa.string(), "-", "driving manoeuvre"),
    Column("experiment", pa.int64(), "-", "experiment number within a case (paper: 1 train, 2 test)"),
    Column("vehicle", pa.string(), "-", "vehicle parameter set name"),
    Column("tire_model", pa.string(), "-", "tire model name"),
    Column("t_s", pa.float64(), "s", "time since the start of the run"),
    Column("x_m", pa.float64(), "m", "CoG east of the run's origin"),
    Column("y_m", pa.float64(), "m", "CoG north of the run's origin"),
    Column("heading_rad", pa.float64(), "rad", "heading, 0 east, positive to the left"),
    Column("vx_true_mps", pa.float64(), "m/s", "true longitudinal speed of the CoG"),
    Column("vy_true_mps", pa.float64(), "m/s", "true lateral speed of the CoG"),
    Column("ax_true_mps2", pa.float64(), "m/s^2", "true longitudinal acceleration of the CoG"),
    Column("ay_true_mps2", pa.float64(), "m/s^2", "true lateral acceleration of the CoG"),
    Column("yaw_rate_true_radps", pa.float64(), "rad/s", "true yaw rate"),
    Column("roll_true_rad", pa.float64(), "rad", "true roll angle, positive right side down"),
    Column("steer_true_rad", pa.float64(), "rad", "true road-wheel steering angle"),
    Column(
        "mu", pa.float64(), "-", "road adhesion coefficient at the vehicle (mean of the two tracks at the CoG): label"
    ),
    *(Column(f"mu_{w}", pa.float64(), "-", f"road adhesion coefficient under wheel {w}") for w in WHEELS),
    *(Column(f"slip_ratio_{w}", pa.float64(), "-", f"slip ratio (eq. 6), wheel {w}") for w in WHEELS),
    *(Column(f"slip_angle_{w}_rad", pa.float64(), "rad", f"slip angle (eq. 8), wheel {w}") for w in WHEELS),
    *(Column(f"fz_{w}_n", pa.float64(), "N", f"vertical load, wheel {w}") for w in WHEELS),
    *(Column(f"fx_{w}_n", pa.float64(), "N", f"longitudinal tire force (wheel frame), wheel {w}") for w in WHEELS),
    *(Column(f"fy_{w}_n", pa.float64(), "N", f"lateral tire force (wheel frame), wheel {w}") for w in WHEELS),
)

TELEMETRY_COLUMNS = tuple(c.name for c in TELEMETRY)
DATASET_SCHEMA = pa.schema([pa.field(c.name, c.type, nullable=not c.required) for c in TELEMETRY + GROUND_TRUTH])

# An estimate as the cloud stores it, publishes it on a vehicle's friction topic and hands it to the map (CONTRACTS 3.4):
# the estimator's output plus where the vehicle was. Offline files (`roadgrip estimate`) carry the first eight.
ESTIMATE = (
    Column("vehicle_id", pa.string(), "-", "the vehicle, as in its telemetry"),
    Column("timestamp_ms", pa.int64(), "ms", "the sample's timestamp, as the input had it"),
    Column("mu", pa.float64(), "-", "most probable road adhesion coefficient"),
    Column("mu_lower", pa.float64(), "-", "5 % quantile: lower end of the 90 % interval"),
    Column("mu_upper", pa.float64(), "-", "95 % quantile: upper end of the 90 % interval"),
    Column("excited", pa.bool_(), "-", "the manoeuvre made mu observable"),
    Column("estimator", pa.string(), "-", "name of the estimator"),
    Column(
        "mu_proven",
        pa.float64(),
        "-",
        "what the car's own acceleration proves (null without the physics guard)",
        required=False,
    ),
    Column("latitude_deg", pa.float64(), "deg", "WGS84 latitude of the sample", required=False),
    Column("longitude_deg", pa.float64(), "deg", "WGS84 longitude of the sample", required=False),
    Column("h3_cell", pa.string(), "-", "H3 cell of the position at the map's resolution", required=False),
)
ESTIMATE_FIELDS = tuple(c.name for c in ESTIMATE)
