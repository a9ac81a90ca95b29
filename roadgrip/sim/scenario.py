"""A scenario: one simulated run, fully described (vehicle, tires, road, mu, driver, duration, seed)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MU_MODES, GradeProfile, MuProfile, Path
from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.params import PAPER_SUV, VehicleParams
from roadgrip.vehicle.tires import DugoffTire, TireModel

SAMPLE_PERIOD_S = 0.1  # telemetry every 100 ms (paper 2.1)


@dataclass(frozen=True, eq=False)
class Scenario:
    """One run. `condition` and `road` label it in the dataset (paper: low/medium/high/increasing/decreasing, straight/
    circular); `seed` drives the sensor noise and biases; `grade` is the road's longitudinal grade; `effects` the
    production-terminal effects of its sensors (off: the paper's CarSim-like setting)."""

    run_id: str
    path: Path
    mu: MuProfile
    speed: SpeedProfile
    condition: str = "custom"
    road: str = "custom"
    vehicle: VehicleParams = PAPER_SUV
    tire: TireModel = field(default_factory=DugoffTire)
    steer: SteerInput | None = None
    duration_s: float = field(default=40.0, metadata=bounded(0.0, 3600.0, low_open=True))
    abs_enabled: bool = True
    tcs_enabled: bool = True
    seed: int = 0
    experiment: int = 1
    manoeuvre: str = "custom"
    grade: GradeProfile = field(default_factory=GradeProfile.flat)
    effects: ProductionEffects = field(default_factory=ProductionEffects.off)

    def __post_init__(self):
        check_bounds(self)
        for name, cls in (
            ("path", Path),
            ("mu", MuProfile),
            ("speed", SpeedProfile),
            ("vehicle", VehicleParams),
            ("tire", TireModel),
            ("grade", GradeProfile),
            ("effects", ProductionEffects),
        ):
            if not isinstance(getattr(self, name), cls):
                raise TypeError(f"Scenario.{name} must be a {cls.__name__}, got {type(getattr(self, name)).__name__}")
        if self.steer is not None and not isinstance(self.steer, SteerInput):
            raise TypeError(f"Scenario.steer must be a SteerInput or None, got {type(self.steer).__name__}")
        if not self.run_id:
            raise ValueError("Scenario.run_id must not be empty")

    @property
    def n_samples(self) -> int:
        return round(self.duration_s / SAMPLE_PERIOD_S)

    def replace(self, **changes) -> Scenario:
        return dataclasses.replace(self, **changes)

    def describe(self) -> dict:
        """A JSON-ready summary for the dataset manifest."""
        return {
            "run_id": self.run_id,
            "condition": self.condition,
            "road": self.road,
            "manoeuvre": self.manoeuvre,
            "experiment": self.experiment,
            "seed": self.seed,
            "duration_s": self.duration_s,
            "vehicle": self.vehicle.to_dict(),
            "tire_model": self.tire.name,
            "tire_shape": self.tire.shape_params(),
            "tire_stiffness_scale": self.tire.stiffness_scale,
            "abs_enabled": self.abs_enabled,
            "tcs_enabled": self.tcs_enabled,
            "path_length_m": self.path.length_m,
            "mu_profile": {
                "mode": self.mu.mode,
                "stations_m": self.mu.stations_m.tolist(),
                "mu_left": self.mu.mu_left.tolist(),
                "mu_right": self.mu.mu_right.tolist(),
            },
            "speed_profile": {
                "times_s": self.speed.times_s.tolist(),
                "speeds_mps": self.speed.speeds_mps.tolist(),
                "acc_active": self.speed.acc_active.tolist(),
            },
            "steer": None if self.steer is None else dataclasses.asdict(self.steer),
            "production_effects": self.effects.to_dict(),
            "grade_profile": {"stations_m": self.grade.stations_m.tolist(), "grade_rad": self.grade.grade_rad.tolist()},
        }


@dataclass
class PackedBatch:
    """Scenarios as the padded arrays the compiled integrator reads (one leading row per run)."""

    vp: np.ndarray
    tp: np.ndarray
    path: np.ndarray
    n_path: np.ndarray
    mu: np.ndarray
    n_mu: np.ndarray
    mu_mode: np.ndarray
    grade: np.ndarray
    n_grade: np.ndarray
    speed: np.ndarray
    n_speed: np.ndarray
    steer: np.ndarray
    flags: np.ndarray


def _pad(tables: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    n = np.array([t.shape[0] for t in tables], dtype=np.int64)
    out = np.zeros((len(tables), int(n.max()), tables[0].shape[1]))
    for i, t in enumerate(tables):
        out[i, : t.shape[0]] = t
    return out, n


def pack(scenarios: list[Scenario]) -> PackedBatch:
    from roadgrip.vehicle.dynamics import pack_vehicle

    path, n_path = _pad([s.path.table() for s in scenarios])
    mu, n_mu = _pad([s.mu.table() for s in scenarios])
    speed, n_speed = _pad([s.speed.table() for s in scenarios])
    grade, n_grade = _pad([s.grade.table() for s in scenarios])
    no_steer = np.array([0.0, 0.0, 0.0, 0.0, 0.0])
    return PackedBatch(
        vp=np.stack([pack_vehicle(s.vehicle) for s in scenarios]),
        tp=np.stack([np.stack([s.tire.row(s.vehicle.tire_front), s.tire.row(s.vehicle.tire_rear)]) for s in scenarios]),
        path=path,
        n_path=n_path,
        mu=mu,
        n_mu=n_mu,
        mu_mode=np.array([MU_MODES[s.mu.mode] for s in scenarios], dtype=np.int64),
        grade=grade,
        n_grade=n_grade,
        speed=speed,
        n_speed=n_speed,
        steer=np.stack([no_steer if s.steer is None else s.steer.row() for s in scenarios]),
        flags=np.array([[s.abs_enabled, s.tcs_enabled] for s in scenarios], dtype=np.int64),
    )
