"""Vehicle and tire parameters: frozen dataclasses in SI units, with the vehicles roadgrip ships.

The field names of `VehicleParams` are the vehicle profile of CONTRACTS 3.2 (mass_kg, wheelbase_m, cg_to_front_axle_m,
cg_height_m, track_front_m, track_rear_m, wheel_radius_m, steering_ratio, drive) plus the optional fields that the simulator
needs, each with a documented default. The reasoning behind every value the paper does not give is in docs/VEHICLES.md.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import yaml

from roadgrip.units import G_MPS2
from roadgrip.validation import bounded, check_bounds, check_choice, from_mapping

DRIVE_LAYOUTS = ("fwd", "rwd", "awd")


@dataclass(frozen=True)
class TireParams:
    """Linear stiffnesses of one tire, normalised by its vertical load (so they scale with Fz).

    C_x = longitudinal_stiffness_per_load * F_z   [N per unit slip ratio]
    C_y = cornering_stiffness_per_load_per_rad * F_z   [N/rad]
    """

    longitudinal_stiffness_per_load: float = field(default=25.0, metadata=bounded(1.0, 100.0))
    cornering_stiffness_per_load_per_rad: float = field(default=16.0, metadata=bounded(1.0, 60.0))
    # the pneumatic trail at zero slip, t0 = a / 3 of the brush model (a the contact patch's half-length: 0.06-0.1 m
    # on car tires, Pacejka, Tyre and Vehicle Dynamics, 3.2): nominal, calibrated per car by pmf (aligning.py)
    pneumatic_trail_m: float = field(default=0.04, metadata=bounded(0.0, 0.2))

    def __post_init__(self):
        check_bounds(self)


@dataclass(frozen=True)
class VehicleParams:
    """A four-wheeled road vehicle. SI units; angles in radians; ISO 8855 axes (x forward, y left, z up)."""

    name: str = "paper-suv"
    mass_kg: float = field(default=2335.0, metadata=bounded(100.0, 40000.0))
    wheelbase_m: float = field(default=3.008, metadata=bounded(0.5, 10.0, low_open=True))
    cg_to_front_axle_m: float = field(default=1.444, metadata=bounded(0.0, 10.0, low_open=True))
    cg_height_m: float = field(default=0.70, metadata=bounded(0.0, 3.0, low_open=True))
    track_front_m: float = field(default=1.70, metadata=bounded(0.5, 3.0))
    track_rear_m: float = field(default=1.71, metadata=bounded(0.5, 3.0))
    wheel_radius_m: float = field(default=0.383, metadata=bounded(0.1, 1.5, low_open=True))
    steering_ratio: float = field(default=16.0, metadata=bounded(1.0, 40.0))
    drive: str = "awd"
    front_drive_share: float = field(default=0.5, metadata=bounded(0.0, 1.0))
    yaw_inertia_kgm2: float = field(default=5830.0, metadata=bounded(10.0, 1.0e6, low_open=True))
    roll_inertia_kgm2: float = field(default=1000.0, metadata=bounded(1.0, 1.0e5, low_open=True))
    unsprung_mass_kg: float = field(default=240.0, metadata=bounded(0.0, 5000.0))
    roll_stiffness_front_nmprad: float = field(default=99000.0, metadata=bounded(1000.0, 5.0e6))
    roll_stiffness_rear_nmprad: float = field(default=81000.0, metadata=bounded(1000.0, 5.0e6))
    roll_damping_nmsprad: float = field(default=10700.0, metadata=bounded(0.0, 1.0e6))
    roll_center_height_front_m: float = field(default=0.10, metadata=bounded(0.0, 1.5))
    roll_center_height_rear_m: float = field(default=0.15, metadata=bounded(0.0, 1.5))
    wheel_inertia_kgm2: float = field(default=1.8, metadata=bounded(0.05, 50.0, low_open=True))
    brake_front_share: float = field(default=0.65, metadata=bounded(0.0, 1.0))
    max_drive_torque_nm: float = field(default=6000.0, metadata=bounded(0.0, 1.0e5))
    max_power_w: float = field(default=250000.0, metadata=bounded(0.0, 5.0e6))
    max_steer_rad: float = field(default=0.6, metadata=bounded(0.05, 1.2))
    drag_coefficient: float = field(default=0.35, metadata=bounded(0.0, 2.0))
    rolling_resistance: float = field(default=0.012, metadata=bounded(0.0, 0.1))
    length_m: float = field(default=5.035, metadata=bounded(1.0, 25.0))
    width_m: float = field(default=1.989, metadata=bounded(0.5, 3.0))
    height_m: float = field(default=1.778, metadata=bounded(0.5, 5.0))
    ground_clearance_m: float = field(default=0.190, metadata=bounded(0.0, 1.0))
    # the caster's mechanical trail at the front wheels, nominal (10-30 mm on passenger cars; the paper SUV's 25 mm
    # a heavy car's larger caster, the catalogue's 18-25 mm: docs/VEHICLES.md)
    mechanical_trail_m: float = field(default=0.025, metadata=bounded(0.0, 0.1))
    tire_front: TireParams = TireParams(25.0, 14.0, 0.045)
    tire_rear: TireParams = TireParams(25.0, 20.0, 0.045)

    def __post_init__(self):
        check_bounds(self)
        check_choice("VehicleParams", "drive", self.drive, set(DRIVE_LAYOUTS))
        if self.cg_to_front_axle_m >= self.wheelbase_m:
            raise ValueError(
                f"VehicleParams.cg_to_front_axle_m must be below wheelbase_m={self.wheelbase_m}, "
                f"got {self.cg_to_front_axle_m!r}"
            )
        if self.unsprung_mass_kg >= self.mass_kg:
            raise ValueError(
                f"VehicleParams.unsprung_mass_kg must be below mass_kg={self.mass_kg}, got {self.unsprung_mass_kg!r}"
            )
        if self.roll_center_height_front_m >= self.cg_height_m or self.roll_center_height_rear_m >= self.cg_height_m:
            raise ValueError(
                "VehicleParams roll centre heights must lie below cg_height_m="
                f"{self.cg_height_m}, got front {self.roll_center_height_front_m!r}, "
                f"rear {self.roll_center_height_rear_m!r}"
            )

    @property
    def cg_to_rear_axle_m(self) -> float:
        return self.wheelbase_m - self.cg_to_front_axle_m

    @property
    def sprung_mass_kg(self) -> float:
        return self.mass_kg - self.unsprung_mass_kg

    @property
    def frontal_area_m2(self) -> float:
        """Frontal area from the outer dimensions, A = 0.84 w h (Wong, Theory of Ground Vehicles, 4th ed., 3.1)."""
        return 0.84 * self.width_m * self.height_m

    @property
    def static_axle_loads_n(self) -> tuple[float, float]:
        """(front, rear) static axle loads on level ground from the moment balance about each axle."""
        weight_n = self.mass_kg * G_MPS2
        return (
            weight_n * self.cg_to_rear_axle_m / self.wheelbase_m,
            weight_n * self.cg_to_front_axle_m / self.wheelbase_m,
        )

    @property
    def drive_split(self) -> tuple[float, float]:
        """Share of the drive torque sent to the (front, rear) axle."""
        front = {"fwd": 1.0, "rwd": 0.0, "awd": self.front_drive_share}[self.drive]
        return front, 1.0 - front

    def replace(self, **changes) -> VehicleParams:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> VehicleParams:
        return from_mapping(cls, data, nested={"tire_front": TireParams, "tire_rear": TireParams})

    def to_yaml(self, path: str | Path) -> None:
        Path(path).write_text(yaml.safe_dump(self.to_dict(), sort_keys=False))

    @classmethod
    def from_yaml(cls, path: str | Path) -> VehicleParams:
        data = yaml.safe_load(Path(path).read_text())
        return cls.from_dict(data)


PAPER_SUV = VehicleParams()

MIDSIZE_SEDAN = VehicleParams(
    name="midsize-sedan",
    mass_kg=1550.0,
    wheelbase_m=2.80,
    cg_to_front_axle_m=1.12,
    cg_height_m=0.55,
    track_front_m=1.58,
    track_rear_m=1.57,
    wheel_radius_m=0.316,
    steering_ratio=15.0,
    drive="fwd",
    front_drive_share=1.0,
    yaw_inertia_kgm2=2600.0,
    roll_inertia_kgm2=550.0,
    unsprung_mass_kg=170.0,
    roll_stiffness_front_nmprad=60000.0,
    roll_stiffness_rear_nmprad=40000.0,
    roll_damping_nmsprad=5200.0,
    roll_center_height_front_m=0.08,
    roll_center_height_rear_m=0.12,
    wheel_inertia_kgm2=1.1,
    brake_front_share=0.70,
    max_drive_torque_nm=3600.0,
    max_power_w=150000.0,
    max_steer_rad=0.6,
    drag_coefficient=0.28,
    rolling_resistance=0.011,
    length_m=4.88,
    width_m=1.84,
    height_m=1.45,
    ground_clearance_m=0.14,
    mechanical_trail_m=0.02,
    tire_front=TireParams(22.0, 15.0, 0.04),
    tire_rear=TireParams(22.0, 21.0, 0.04),
)

COMPACT_HATCHBACK = VehicleParams(
    name="compact-hatchback",
    mass_kg=1250.0,
    wheelbase_m=2.55,
    cg_to_front_axle_m=0.97,
    cg_height_m=0.52,
    track_front_m=1.52,
    track_rear_m=1.50,
    wheel_radius_m=0.300,
    steering_ratio=14.5,
    drive="fwd",
    front_drive_share=1.0,
    yaw_inertia_kgm2=1750.0,
    roll_inertia_kgm2=400.0,
    unsprung_mass_kg=140.0,
    roll_stiffness_front_nmprad=48000.0,
    roll_stiffness_rear_nmprad=30000.0,
    roll_damping_nmsprad=4000.0,
    roll_center_height_front_m=0.07,
    roll_center_height_rear_m=0.11,
    wheel_inertia_kgm2=0.9,
    brake_front_share=0.72,
    max_drive_torque_nm=2600.0,
    max_power_w=90000.0,
    max_steer_rad=0.6,
    drag_coefficient=0.31,
    rolling_resistance=0.011,
    length_m=4.28,
    width_m=1.79,
    height_m=1.46,
    ground_clearance_m=0.14,
    mechanical_trail_m=0.018,
    tire_front=TireParams(21.0, 15.0, 0.035),
    tire_rear=TireParams(21.0, 20.0, 0.035),
)

VEHICLES = {v.name: v for v in (PAPER_SUV, MIDSIZE_SEDAN, COMPACT_HATCHBACK)}


def vehicle_by_name(name: str) -> VehicleParams:
    check_choice("vehicle", "name", name, set(VEHICLES))
    return VEHICLES[name]
