"""Sensor models: from the simulator's true signals to what a vehicle's terminal sends (wire format v1, every 100 ms).

Each signal gets a per-run constant bias drawn once and white noise drawn per sample, both from the run's seeded generator;
the standard deviations below are typical of production sensors (see docs/SIMULATOR.md for the sources):

| signal                     | bias (1 sigma)  | noise (1 sigma) | model                                                   |
|----------------------------|-----------------|-----------------|---------------------------------------------------------|
| speed_mps                  | 0.5 % of speed  | 0.05 m/s        | speed from the wheel-speed ECU, tire-wear scale error    |
| accel_lon/lat_mps2         | 0.05 m/s^2      | 0.05 m/s^2      | MEMS IMU on the sprung mass: the lateral channel reads    |
|                            |                 |                 | a_y + g sin(roll), the specific force of a rolled body   |
| yaw_rate_radps             | 0.002 rad/s     | 0.002 rad/s     | MEMS gyro (about 0.1 deg/s)                              |
| steering_wheel_angle_rad   | 0.5 deg         | 0.2 deg         | steering-angle sensor, angle = road-wheel angle x ratio  |
| wheel_speed_*_radps        | -               | 0.02 rad/s      | wheel-speed sensor (tone wheel) jitter                   |
| lateral_speed_mps          | -               | 0.02 m/s        | optical ground-speed sensor of a test vehicle            |
| latitude/longitude_deg     | -               | 1.5 m           | GNSS, first-order Gauss-Markov error with 10 s time constant |

On top of these, a run's `ProductionEffects` (roadgrip/sim/production.py) may put in what a series car's terminal does:
speed computed from the wheel speeds, accelerometer mounting angle, bias and body pitch, per-wheel rolling radius, CAN
resolution and time offsets between signal groups. With every effect off (the default) nothing here changes. The
optional channels (GNSS speed, forces, steering torques: roadgrip/sim/channels.py) are sent where the effects switch
them on, NaN (not sent) otherwise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pymap3d

from roadgrip.data.schema import CHANNEL_NAMES
from roadgrip.sim.channels import ChannelModel, optional_channels
from roadgrip.sim.production import ProductionEffects, ecu_signals, sensed_truth
from roadgrip.units import G_MPS2, deg_to_rad
from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.params import VehicleParams
from roadgrip.vehicle.tires.base import TireModel

HEBEI_ORIGIN = (38.0428, 114.5149)  # Shijiazhuang, Hebei Province: where the paper's vehicle-road-cloud system runs


@dataclass(frozen=True)
class SensorModel:
    """Noise and bias of the terminal's signals (1 sigma, SI units), and where the local road frame sits on the globe."""

    speed_scale_bias: float = field(default=0.005, metadata=bounded(0.0, 0.1))
    speed_noise_mps: float = field(default=0.05, metadata=bounded(0.0, 5.0))
    accel_bias_mps2: float = field(default=0.05, metadata=bounded(0.0, 2.0))
    accel_noise_mps2: float = field(default=0.05, metadata=bounded(0.0, 5.0))
    yaw_rate_bias_radps: float = field(default=0.002, metadata=bounded(0.0, 0.1))
    yaw_rate_noise_radps: float = field(default=0.002, metadata=bounded(0.0, 0.5))
    steering_bias_rad: float = field(default=deg_to_rad(0.5), metadata=bounded(0.0, 0.5))
    steering_noise_rad: float = field(default=deg_to_rad(0.2), metadata=bounded(0.0, 0.5))
    wheel_speed_noise_radps: float = field(default=0.02, metadata=bounded(0.0, 5.0))
    lateral_speed_noise_mps: float = field(default=0.02, metadata=bounded(0.0, 2.0))
    gnss_noise_m: float = field(default=1.5, metadata=bounded(0.0, 100.0))
    gnss_time_constant_s: float = field(default=10.0, metadata=bounded(0.0, 1000.0, low_open=True))
    origin_lat_deg: float = field(default=HEBEI_ORIGIN[0], metadata=bounded(-90.0, 90.0))
    origin_lon_deg: float = field(default=HEBEI_ORIGIN[1], metadata=bounded(-180.0, 180.0))
    channels: ChannelModel = field(
        default_factory=ChannelModel
    )  # the optional channels' error models, where a run's effects send them

    def __post_init__(self):
        check_bounds(self)

    @classmethod
    def noiseless(cls, **changes) -> SensorModel:
        zero = {
            f: 0.0
            for f in (
                "speed_scale_bias",
                "speed_noise_mps",
                "accel_bias_mps2",
                "accel_noise_mps2",
                "yaw_rate_bias_radps",
                "yaw_rate_noise_radps",
                "steering_bias_rad",
                "steering_noise_rad",
                "wheel_speed_noise_radps",
                "lateral_speed_noise_mps",
                "gnss_noise_m",
            )
        }
        return cls(**(zero | changes))

    def measure(
        self,
        truth: dict[str, np.ndarray],
        steering_ratio: float,
        sample_period_s: float,
        rng: np.random.Generator,
        *,
        effects: ProductionEffects | None = None,
        vehicle: VehicleParams | None = None,
        tire: TireModel | None = None,
    ) -> dict[str, np.ndarray]:
        """Telemetry signals of one run from its true signals (arrays over samples, keys as in integrator.CHANNELS).

        With production `effects` (which need the `vehicle`: nominal wheel radius and drive layout), the sensors see
        the truth through them (`production.sensed_truth`) and the ECU's speed and CAN resolution rewrite the speeds
        (`production.ecu_signals`). Their per-run draws come from a generator spawned from `rng`, so the base model's
        draws are the same with the effects on or off. The optional channels' steering torques need the run's `tire`
        model too (the pneumatic trail follows its cornering stiffness)."""
        production = effects is not None and effects.any_sensor_effect
        true = truth  # the optional channels have their own delays (channels.py), not the CAN groups' offsets
        if production:
            if vehicle is None:
                raise ValueError(
                    "SensorModel.measure: production effects need the vehicle (wheel radius, drive layout)"
                )
            truth = sensed_truth(truth, effects, effects.draw(rng.spawn(1)[0]))
        n = truth["t_s"].size

        def noisy(x, bias_sigma, noise_sigma):
            return x + rng.normal(0.0, bias_sigma) + rng.normal(0.0, noise_sigma, n)

        out = {
            "speed_mps": truth["vx_mps"] * (1.0 + rng.normal(0.0, self.speed_scale_bias))
            + rng.normal(0.0, self.speed_noise_mps, n),
            "accel_lon_mps2": noisy(truth["ax_mps2"], self.accel_bias_mps2, self.accel_noise_mps2),
            "accel_lat_mps2": noisy(
                truth["ay_mps2"] + G_MPS2 * np.sin(truth["roll_rad"]), self.accel_bias_mps2, self.accel_noise_mps2
            ),
            "yaw_rate_radps": noisy(truth["yaw_rate_radps"], self.yaw_rate_bias_radps, self.yaw_rate_noise_radps),
            "steering_wheel_angle_rad": noisy(
                truth["steer_rad"] * steering_ratio, self.steering_bias_rad, self.steering_noise_rad
            ),
            "lateral_speed_mps": truth["vy_mps"] + rng.normal(0.0, self.lateral_speed_noise_mps, n),
        }
        for w in ("fl", "fr", "rl", "rr"):
            out[f"wheel_speed_{w}_radps"] = truth[f"omega_{w}_radps"] + rng.normal(0.0, self.wheel_speed_noise_radps, n)
        east = truth["x_m"] + self._gauss_markov(n, sample_period_s, rng)
        north = truth["y_m"] + self._gauss_markov(n, sample_period_s, rng)
        lat, lon, _ = pymap3d.enu2geodetic(east, north, np.zeros(n), self.origin_lat_deg, self.origin_lon_deg, 0.0)
        out["latitude_deg"], out["longitude_deg"] = np.asarray(lat), np.asarray(lon)
        if production:
            ecu_signals(out, truth, effects, vehicle.wheel_radius_m, vehicle.drive_split[0], sample_period_s)
        if effects is not None and effects.any_channel:
            if vehicle is None:
                raise ValueError("SensorModel.measure: the optional channels need the vehicle (steering, tires)")
            # a child generator of their own, so the base signals' draws stay as they were
            out |= optional_channels(
                true,
                vehicle,
                sample_period_s,
                rng.spawn(1)[0],
                gnss=effects.gnss_speed,
                forces=effects.force_signals,
                steering=effects.steering_torque,
                model=self.channels,
                tire=tire,
            )
        else:
            out |= {name: np.full(n, np.nan) for name in CHANNEL_NAMES}  # not sent
        return out

    def _gauss_markov(self, n, sample_period_s, rng):
        """First-order Gauss-Markov error with stationary std gnss_noise_m (zero when the noise is off)."""
        phi = math.exp(-sample_period_s / self.gnss_time_constant_s)
        drive = rng.normal(0.0, self.gnss_noise_m * math.sqrt(1.0 - phi * phi), n)
        err = np.empty(n)
        state = rng.normal(0.0, self.gnss_noise_m)
        for k in range(n):
            state = phi * state + drive[k]
            err[k] = state
        return err
