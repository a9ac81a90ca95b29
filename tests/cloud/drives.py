"""Simulated drives for the cloud tests: a straight road near the Hebei origin heading east with a slippery patch
between PATCH_M[0] and PATCH_M[1], driven at cruising speed with hard braking on the patch (the ABS works there, so mu is
observable)."""

from __future__ import annotations

import functools

import h3
import numpy as np
import pyarrow as pa
import pymap3d

from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.sensors import HEBEI_ORIGIN
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import vehicle_by_name

PATCH_M = (250.0, 400.0)
DRY_MU = 0.9


@functools.cache
def patch_drive(
    patch_mu: float, seed: int, vehicle: str = "paper-suv", brake_s: float = 10.5, production: bool = False
) -> pa.Table:
    """One 30 s run: 20 m/s at the start, 25 m/s from 4 s (90 m), braking to 6 m/s in 3 s from `brake_s` (the default
    10.5 s is 252 m: the patch's first metres; 13 s is 315 m). `production`: every production-terminal effect on
    (speed from the wheels, accelerometer bias and tilt, radius spread, CAN resolution, time offsets) on a road that
    climbs 2 % and falls 2 %."""
    mu = np.array([DRY_MU, patch_mu, DRY_MU])
    scenario = Scenario(
        run_id=f"patch-{patch_mu}-{seed}-{vehicle}-{brake_s}",
        path=Path.straight(900.0),
        mu=MuProfile(np.array([0.0, *PATCH_M]), mu, mu, "step"),
        speed=SpeedProfile(np.array([0.0, 4.0, brake_s, brake_s + 3.0, 30.0]), np.array([20.0, 25.0, 25.0, 6.0, 6.0])),
        vehicle=vehicle_by_name(vehicle),
        duration_s=30.0,
        seed=seed,
        **(
            {"effects": ProductionEffects.production(), "grade": GradeProfile([0.0, 450.0, 900.0], [0.02, -0.02, 0.0])}
            if production
            else {}
        ),
    )
    return simulate([scenario])


def patch_cells(resolution: int = 10) -> set[str]:
    """Every cell the road crosses between the patch's ends (metres east of the Hebei origin)."""
    cells = set()
    for east in np.arange(PATCH_M[0], PATCH_M[1] + 1.0, 1.0):
        lat, lon, _ = pymap3d.enu2geodetic(east, 0.0, 0.0, *HEBEI_ORIGIN, 0.0)
        cells.add(h3.latlng_to_cell(float(lat), float(lon), resolution))
    return cells
