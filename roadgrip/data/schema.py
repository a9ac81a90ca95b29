"""The one source of truth for column names, types and units: telemetry wire format v1 (CONTRACTS 3.1), the simulation
dataset (CONTRACTS 3.3), the estimate (CONTRACTS 3.4) as the cloud stores and publishes it, and what a vehicle that
estimates on board sends instead of its telemetry: the friction observation and the heartbeat (CONTRACTS 3.7)."""

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

# A friction observation (CONTRACTS 3.7): what `roadgrip edge` (roadgrip/edge/) sends for one pass of the vehicle
# through one H3 cell of the map (roadgrip/cloud/domain/passes.py) where it had evidence, instead of the pass's raw
# telemetry. The domain turns it back into the rows of that pass (roadgrip/cloud/domain/observations.py). mu,
# mu_lower and mu_upper are VSS Vehicle.ADAS.ESC.RoadFriction.MostProbable / LowerBound / UpperBound (as a fraction,
# not VSS's percent).
EVIDENCE_KINDS = ("bound", "abs", "tcs", "esc", "lateral", "slip_slope")
OBSERVATION = (
    Column("vehicle_id", pa.string(), "-", "the vehicle, as in its telemetry"),
    Column("h3_cell", pa.string(), "-", "H3 cell of the pass, at the map's resolution"),
    Column("first_ms", pa.int64(), "ms", "the pass's first estimated sample, ms since the Unix epoch"),
    Column("last_ms", pa.int64(), "ms", "the pass's last estimated sample: the pass's time"),
    Column("latitude_deg", pa.float64(), "deg", "WGS84 latitude of the pass's telling sample"),
    Column("longitude_deg", pa.float64(), "deg", "WGS84 longitude of the pass's telling sample"),
    Column("mu", pa.float64(), "-", "most probable mu: median over the excited estimates (else the last estimate)"),
    Column("mu_lower", pa.float64(), "-", "5 % end: median of the excited estimates' (else the last estimate's)"),
    Column("mu_upper", pa.float64(), "-", "95 % end: median of the excited estimates' (else the last estimate's)"),
    Column(
        "mu_proven", pa.float64(), "-", "the largest bound the car's acceleration proved in the pass", required=False
    ),
    Column("excited", pa.bool_(), "-", "an estimate of the pass was excited"),
    Column("n_estimates", pa.int64(), "-", "estimates in the pass"),
    Column("n_excited", pa.int64(), "-", "excited estimates in the pass"),
    Column("evidence", pa.list_(pa.string()), "-", f"kinds of evidence in the pass, of {EVIDENCE_KINDS}"),
    Column("channels", pa.list_(pa.string()), "-", "the optional telemetry fields (CONTRACTS 3.1) the car has"),
    Column("vehicle_class", pa.string(), "-", "the vehicle's profile name (CONTRACTS 3.2)"),
    Column("estimator", pa.string(), "-", "name of the estimator on board"),
)
OBSERVATION_FIELDS = tuple(c.name for c in OBSERVATION)

# The sparse heartbeat of an edge vehicle (CONTRACTS 3.7): that it runs, where it is, what waits in its outbox.
HEARTBEAT = (
    Column("vehicle_id", pa.string(), "-", "the vehicle"),
    Column("timestamp_ms", pa.int64(), "ms", "the newest sample's timestamp, ms since the Unix epoch"),
    Column("latitude_deg", pa.float64(), "deg", "WGS84 latitude of the newest sample", required=False),
    Column("longitude_deg", pa.float64(), "deg", "WGS84 longitude of the newest sample", required=False),
    Column("n_samples", pa.int64(), "-", "samples estimated since the previous heartbeat"),
    Column("n_observations", pa.int64(), "-", "observations made since the previous heartbeat"),
    Column("outbox_pending", pa.int64(), "-", "messages waiting in the outbox for their PUBACK"),
    Column("outbox_dropped", pa.int64(), "-", "messages the outbox dropped at its limit, since it was made"),
)
HEARTBEAT_FIELDS = tuple(c.name for c in HEARTBEAT)
