"""The drives the estimator contract suite (test_contract.py) feeds every estimator: short simulated runs with every
production-terminal effect on (speed from the wheels, accelerometer bias, tilt and pitch, radius spread, CAN resolution,
time offsets, road grade, tire stiffness), each as a terminal sends it and as `roadgrip estimate` reads it.

- abs-brake: the paper's SUV brakes from 22 m/s to a stop on a wet road (mu 0.4): ABS acts for most of it; it sends
  every optional channel (GNSS speed, drive and brake force, steering torques: CONTRACTS 3.1);
- corner: a mid-size sedan speeds up on a 60 m circle of dry asphalt to 0.6 g of lateral acceleration; every optional
  channel too;
- cruise: a compact hatchback cruises gently up a 2 % grade (nothing to judge mu by).

Together 35 s of data (350 samples), so that every check of the suite over every estimator runs in seconds.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.data.telemetry import validate_telemetry
from roadgrip.fleet.terminal import wire_samples
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV, VehicleParams

START_MS = 1_767_225_600_000


@dataclass(frozen=True)
class Drive:
    """One vehicle's drive: `samples` as its terminal sends them (wire format v1 dicts, the streaming input), `table`
    and `segments` as `roadgrip estimate` validates them (the batch input), the same rows in the same order."""

    vehicle_id: str
    vehicle: VehicleParams
    samples: tuple[dict, ...]
    table: pa.Table
    segments: np.ndarray


def _scenarios() -> list[Scenario]:
    effects = ProductionEffects.production()
    return [
        Scenario(
            run_id="abs-brake",
            path=Path.straight(400.0),
            mu=MuProfile.uniform(0.4),
            speed=SpeedProfile([0.0, 3.0, 3.3, 8.0], [22.0, 22.0, 0.0, 0.0]),
            vehicle=PAPER_SUV,
            duration_s=8.0,
            seed=3,
            effects=effects.with_channels(),
        ),
        Scenario(
            run_id="corner",
            path=Path.circle(60.0, 400.0),
            mu=MuProfile.uniform(0.8),
            speed=SpeedProfile([0.0, 12.0], [10.0, 19.0]),
            vehicle=MIDSIZE_SEDAN,
            duration_s=12.0,
            seed=4,
            effects=effects.with_channels(),
        ),
        Scenario(
            run_id="cruise",
            path=Path.straight(600.0),
            mu=MuProfile.uniform(0.9),
            speed=SpeedProfile([0.0, 5.0, 10.0, 15.0], [20.0, 22.0, 22.0, 18.0]),
            vehicle=COMPACT_HATCHBACK,
            duration_s=15.0,
            seed=5,
            effects=effects,
            grade=GradeProfile.uniform(0.02),
        ),
    ]


@functools.cache
def contract_drives() -> tuple[Drive, ...]:
    """The three drives, each under its own vehicle_id (its run_id), all starting at START_MS."""
    scenarios = _scenarios()
    table = simulate(scenarios)
    drives = []
    for scenario in scenarios:
        samples = wire_samples(table.filter(pc.equal(table["run_id"], scenario.run_id)), scenario.run_id, START_MS)
        batch = validate_telemetry(pa.Table.from_pylist(samples), source=scenario.run_id)
        if batch.rejections or batch.table.num_rows != len(samples) or len(set(batch.segments.tolist())) != 1:
            raise AssertionError(
                f"drive {scenario.run_id}: the validator changed the input ({batch.warnings}, "
                f"{len(batch.rejections)} rejections)"
            )
        drives.append(Drive(scenario.run_id, scenario.vehicle, tuple(samples), batch.table, batch.segments))
    return tuple(drives)
