"""Production-terminal realism: what a series car's terminal does to its signals that a test vehicle's does not.

A production terminal computes its speed from the wheel speeds (so speed - wheel speed carries no slip), its
accelerometer carries a mounting angle, a bias and the gravity of the body's pitch, its tires are worn and unknown, and
its CAN signals are quantised and arrive with offsets between them. `ProductionEffects` switches each effect and sets its
size; a scenario carries one (`Scenario.effects`): off for the `paper` preset (the paper's CarSim-like setting), on for
`random` and the generalization presets (`ProductionEffects.production()`). docs/SIMULATOR.md has the ranges and sources.

| effect (field)                               | production()        | model                                               |
|----------------------------------------------|---------------------|-----------------------------------------------------|
| speed from the wheels (speed_from_wheels)    | on; 1.3 g           | `ecu_speed`: undriven wheels' mean x nominal radius |
|   (reference_decel_max_mps2)                 |                     | driving; braking: the fastest wheel, falling at     |
|                                              |                     | most as the accelerometer says and at most 1.3 g    |
| accelerometer mounting (accel_mount_max_rad) | +-2 deg, uniform    | pitch and roll angles: + g sin(angle)               |
| accelerometer bias (accel_bias_max_mps2)     | +-0.2 m/s^2         | constant per run and channel                        |
| body pitch (pitch_gradient_rad_per_mps2)     | 1.5 deg/g           | nose-up angle = gradient x a_x: + g sin(angle)      |
| rolling-radius spread (wheel_radius_spread)  | +-2 %, per wheel    | reported omega x r_nominal / r_actual               |
| CAN resolution (wheel_speed_resolution_kmh)  | 0.01 km/h           | wheel speeds and speed rounded to the step          |
| time offsets (time_offset_max_s)             | +-50 ms, per group  | wheel / IMU / steering groups read at t + offset    |
| road grade (grade_max_rad)                   | +-4 % (+-0.04 rad)  | drawn by the preset, in the dynamics (roads.py)     |
| tire stiffness (tire_stiffness_spread)       | +-30 %              | drawn by the preset: TireModel.stiffness_scale      |
| optional channels (gnss_speed, force_signals, | off; the random and | GNSS Doppler speed, drive and brake force, steering |
|   steering_torque)                           | generalization      | torques (roadgrip/sim/channels.py), else not sent   |
|                                              | presets: half the   |                                                     |
|                                              | runs                |                                                     |

Each random quantity is drawn from the run's generator after the base sensor model's draws, all of them whichever effects
are on (so switching one effect never changes another's draw), and none when every sensor effect is off (so a run with
the effects off is bit for bit what it was before they existed).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields

import numpy as np

from roadgrip.units import G_MPS2, deg_to_rad, kmh_to_mps
from roadgrip.validation import bounded, check_bounds

WHEELS = ("fl", "fr", "rl", "rr")
AWD_ACCELERATING_MPS2 = (
    0.5  # an AWD car's ECU takes its slowest wheel while the wheels' mean speeds up faster than this
)
SENSOR_FIELDS = (
    "speed_from_wheels",
    "accel_mount_max_rad",
    "accel_bias_max_mps2",
    "pitch_gradient_rad_per_mps2",
    "wheel_radius_spread",
    "wheel_speed_resolution_kmh",
    "time_offset_max_s",
)
CHANNEL_FLAGS = ("gnss_speed", "force_signals", "steering_torque")  # the optional channels a run sends


@dataclass(frozen=True)
class ProductionEffects:
    """Which production-terminal effects a run has, and how large (0 or False: off). Ranges are half-widths of uniform
    per-run draws."""

    speed_from_wheels: bool = False
    reference_decel_max_mps2: float = field(default=1.3 * G_MPS2, metadata=bounded(1.0, 50.0))
    accel_mount_max_rad: float = field(default=0.0, metadata=bounded(0.0, 0.2))
    accel_bias_max_mps2: float = field(default=0.0, metadata=bounded(0.0, 2.0))
    pitch_gradient_rad_per_mps2: float = field(default=0.0, metadata=bounded(0.0, 0.02))
    wheel_radius_spread: float = field(default=0.0, metadata=bounded(0.0, 0.2))
    wheel_speed_resolution_kmh: float = field(default=0.0, metadata=bounded(0.0, 1.0))
    time_offset_max_s: float = field(default=0.0, metadata=bounded(0.0, 0.5))
    grade_max_rad: float = field(default=0.0, metadata=bounded(0.0, 0.3))
    tire_stiffness_spread: float = field(default=0.0, metadata=bounded(0.0, 0.6))
    # the optional channels (roadgrip/sim/channels.py has their error models): off means not sent
    gnss_speed: bool = False
    force_signals: bool = False
    steering_torque: bool = False

    def __post_init__(self):
        check_bounds(self)
        for name in ("speed_from_wheels", *CHANNEL_FLAGS):
            if not isinstance(getattr(self, name), bool):
                raise TypeError(f"ProductionEffects.{name} must be a bool, got {getattr(self, name)!r}")

    def with_channels(self, on: bool = True) -> ProductionEffects:
        """These effects with every optional channel switched on (or off)."""
        return dataclasses.replace(self, **dict.fromkeys(CHANNEL_FLAGS, on))

    @property
    def any_channel(self) -> bool:
        return any(getattr(self, name) for name in CHANNEL_FLAGS)

    @classmethod
    def off(cls) -> ProductionEffects:
        return cls()

    @classmethod
    def production(cls, **changes) -> ProductionEffects:
        """Every effect on, at the sizes of docs/SIMULATOR.md ("Production-terminal realism")."""
        return cls(
            **(
                {
                    "speed_from_wheels": True,
                    "accel_mount_max_rad": deg_to_rad(2.0),
                    "accel_bias_max_mps2": 0.2,
                    "pitch_gradient_rad_per_mps2": deg_to_rad(1.5) / G_MPS2,
                    "wheel_radius_spread": 0.02,
                    "wheel_speed_resolution_kmh": 0.01,
                    "time_offset_max_s": 0.05,
                    "grade_max_rad": 0.04,
                    "tire_stiffness_spread": 0.3,
                }
                | changes
            )
        )

    @property
    def any_sensor_effect(self) -> bool:
        return any(bool(getattr(self, name)) for name in SENSOR_FIELDS)

    def to_dict(self) -> dict:
        return {f.name: getattr(self, f.name) for f in fields(self)}

    def draw(self, rng: np.random.Generator) -> ProductionDraw:
        """The per-run quantities, each a uniform draw scaled by its half-width (drawn even when that is 0)."""
        u = rng.uniform(-1.0, 1.0, 11)
        return ProductionDraw(
            radius_error=self.wheel_radius_spread * u[0:4],
            time_offset_s=self.time_offset_max_s * u[4:7],
            mount_pitch_rad=self.accel_mount_max_rad * u[7],
            mount_roll_rad=self.accel_mount_max_rad * u[8],
            accel_bias_mps2=self.accel_bias_max_mps2 * u[9:11],
        )


@dataclass(frozen=True, eq=False)
class ProductionDraw:
    """One run's draw: per-wheel rolling-radius error (r_actual / r_nominal - 1, fl fr rl rr), time offsets of the wheel,
    IMU and steering groups (s, the signal is read at t + offset), accelerometer mounting angles (nose up, right side
    down) and biases (longitudinal, lateral)."""

    radius_error: np.ndarray
    time_offset_s: np.ndarray
    mount_pitch_rad: float
    mount_roll_rad: float
    accel_bias_mps2: np.ndarray


def shifted(t_s: np.ndarray, x: np.ndarray, offset_s: float) -> np.ndarray:
    """x read at t + offset (linear between samples, the end values beyond them); x itself when the offset is 0."""
    if offset_s == 0.0:
        return x
    return np.interp(t_s + offset_s, t_s, x)


def quantised(speed_mps: np.ndarray, resolution_kmh: float) -> np.ndarray:
    """A speed rounded to a CAN signal's resolution in km/h (unchanged when the resolution is 0)."""
    if resolution_kmh == 0.0:
        return speed_mps
    step_mps = kmh_to_mps(resolution_kmh)
    return np.round(speed_mps / step_mps) * step_mps


def ecu_speed(
    wheel_speed_mps: np.ndarray,
    braking: np.ndarray,
    front_drive_share: float,
    sample_period_s: float,
    reference_decel_max_mps2: float,
    accel_lon_mps2: np.ndarray | None = None,
) -> np.ndarray:
    """Vehicle speed as a production ABS/ESC ECU computes it from its wheel speeds (m/s, shape (n, 4), fl fr rl rr).

    Driving (not braking): the mean of the undriven wheels (FWD: the rear ones, RWD: the front ones), which roll freely;
    an AWD car has none, so the mean of all four, or the slowest while the wheels' mean speeds up faster than
    AWD_ACCELERATING_MPS2 (the least drive slip). Braking (the brake-light switch): a reference speed that follows the
    fastest wheel but falls at most reference_decel_max_mps2, so that locked or deeply slipping wheels do not pull it
    down (Bosch, Automotive Handbook: ABS reference speed; evaluated here at the sample rate). Given the ECU's own
    longitudinal accelerometer (`accel_lon_mps2`, as ESC units have), the reference falls no faster than it says
    (and never faster than reference_decel_max_mps2): with every wheel locked it is the accelerometer's integral."""
    n = wheel_speed_mps.shape[0]
    if front_drive_share >= 1.0:
        driving = wheel_speed_mps[:, 2:4].mean(axis=1)
    elif front_drive_share <= 0.0:
        driving = wheel_speed_mps[:, 0:2].mean(axis=1)
    else:
        mean = wheel_speed_mps.mean(axis=1)
        rising = np.zeros(n, dtype=bool)
        rising[1:] = np.diff(mean) > AWD_ACCELERATING_MPS2 * sample_period_s
        driving = np.where(rising, wheel_speed_mps.min(axis=1), mean)
    fastest = wheel_speed_mps.max(axis=1)
    speed = driving.copy()
    decel = np.full(n, reference_decel_max_mps2)
    if accel_lon_mps2 is not None:
        decel = np.clip(-accel_lon_mps2, 0.0, reference_decel_max_mps2)
    previous = fastest[0]
    for k in range(n):
        if braking[k]:
            speed[k] = max(fastest[k], previous - decel[k] * sample_period_s)
        previous = speed[k]
    return np.maximum(speed, 0.0)


def sensed_truth(
    truth: dict[str, np.ndarray], effects: ProductionEffects, draw: ProductionDraw
) -> dict[str, np.ndarray]:
    """The true signals as the production sensors see them, before the base model's bias and noise: each group read at
    t + its offset, each wheel spinning as a tire of radius r_nominal (1 + e) does, the accelerometer tilted and biased.
    A signal whose effects are all off is the same array as in `truth`."""
    t = truth["t_s"]
    seen = dict(truth)
    wheel_off, imu_off, steer_off = (float(x) for x in draw.time_offset_s)
    for name in ("vx_mps", "brake_active", *(f"omega_{w}_radps" for w in WHEELS)):
        seen[name] = shifted(t, truth[name], wheel_off)
    for name in ("ax_mps2", "ay_mps2", "roll_rad", "grade_rad", "yaw_rate_radps"):
        seen[name] = shifted(t, truth[name], imu_off)
    seen["steer_rad"] = shifted(t, truth["steer_rad"], steer_off)
    if effects.wheel_radius_spread:
        # the dynamics roll on the nominal radius; at the same ground speed the real tire, r_actual = r_nominal (1 + e),
        # spins 1 / (1 + e) times as fast, and the wheel-speed sensor counts exactly that
        for i, w in enumerate(WHEELS):
            seen[f"omega_{w}_radps"] = seen[f"omega_{w}_radps"] / (1.0 + draw.radius_error[i])
    if effects.accel_mount_max_rad or effects.pitch_gradient_rad_per_mps2 or effects.accel_bias_max_mps2:
        ax = seen["ax_mps2"]
        # the sensor's x axis is tilted nose up by its mounting angle plus the body's pitch (squat when accelerating,
        # dive when braking); it reads the specific force along it, a_x cos(theta) + g cos(grade) sin(theta)
        theta = draw.mount_pitch_rad + effects.pitch_gradient_rad_per_mps2 * ax
        seen["ax_mps2"] = (
            ax * np.cos(theta) + G_MPS2 * np.cos(seen["grade_rad"]) * np.sin(theta) + draw.accel_bias_mps2[0]
        )
        # the lateral channel reads a_y + g sin(roll) (SensorModel): its roll is the body's plus the mounting angle
        seen["roll_rad"] = seen["roll_rad"] + draw.mount_roll_rad
        seen["ay_mps2"] = seen["ay_mps2"] + draw.accel_bias_mps2[1]
    return seen


def ecu_signals(
    out: dict[str, np.ndarray],
    truth_seen: dict[str, np.ndarray],
    effects: ProductionEffects,
    wheel_radius_m: float,
    front_drive_share: float,
    sample_period_s: float,
) -> None:
    """Rewrite the measured speed and wheel speeds in `out` as the ECU sends them: the speed from the (noisy) wheel
    speeds (`ecu_speed`), then both rounded to the CAN resolution (in km/h at the nominal radius)."""
    if effects.speed_from_wheels:
        wheel_mps = np.column_stack([out[f"wheel_speed_{w}_radps"] for w in WHEELS]) * wheel_radius_m
        out["speed_mps"] = ecu_speed(
            wheel_mps,
            truth_seen["brake_active"] > 0.5,
            front_drive_share,
            sample_period_s,
            effects.reference_decel_max_mps2,
            out["accel_lon_mps2"],
        )
    resolution = effects.wheel_speed_resolution_kmh
    if resolution:
        for w in WHEELS:
            name = f"wheel_speed_{w}_radps"
            out[name] = quantised(out[name] * wheel_radius_m, resolution) / wheel_radius_m
        out["speed_mps"] = quantised(out["speed_mps"], resolution)


def describe_draw(draw: ProductionDraw) -> dict:
    """A JSON-ready record of one run's draw (for logs and tests)."""
    return {
        "radius_error": draw.radius_error.tolist(),
        "time_offset_s": draw.time_offset_s.tolist(),
        "mount_pitch_rad": draw.mount_pitch_rad,
        "mount_roll_rad": draw.mount_roll_rad,
        "accel_bias_mps2": draw.accel_bias_mps2.tolist(),
        "mount_pitch_deg": math.degrees(draw.mount_pitch_rad),
    }
