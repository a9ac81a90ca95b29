"""A fleet of simulated vehicles on a road network: plan their drives, simulate them, and stream their telemetry to the
cloud at 10 Hz, in real time or faster.

Each vehicle (kinds cycling over roadgrip.vehicle.params.VEHICLES) takes a road of the network, joins it at the road's
cruising speed (vehicles on a network are moving: no standing start), and brakes now and then: a share of the vehicles
brakes where a slippery patch lies on their road (a queue, a hazard ahead: the braking that makes the patch's
adhesion observable), the others at random places. A braking is a deceleration of `BRAKE_MPS2` to 40 % of the cruising
speed, then an acceleration back at `REACCELERATE_MPS2`.

Time: the drives are simulated first (the simulator runs thousands of times faster than real time), then sent by
`roadgrip.fleet.replay.replay`, which paces samples by their timestamps: sample k of every vehicle goes out at
start + k x 100 ms / speed. `timeline` gives it the timestamp start + k x 100 ms - D (1 - 1/speed), D the longest
drive: live timestamps at speed 1, and never ahead of the sending clock when faster (a fast replay of a drive that
just happened), so that the cloud's future-timestamp check holds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import pyarrow.compute as pc

from roadgrip.fleet.network import Network, Road
from roadgrip.fleet.terminal import wire_samples
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import VEHICLES, VehicleParams

BRAKE_MPS2 = 5.0  # a firm stop on a dry road; ABS works on a slippery one
REACCELERATE_MPS2 = 1.5
LOW_SPEED_SHARE = 0.4
SAMPLE_PERIOD_MS = 100
ROUTE_END_MARGIN_M = 20.0
SLIPPERY_MU = 0.4  # a patch below this is what the warnings are for (the cloud's default threshold)


@dataclass(frozen=True)
class VehiclePlan:
    vehicle_id: str
    vehicle: VehicleParams
    road: Road
    scenario: Scenario
    brakes_at_m: tuple[float, ...]  # stations where braking starts


def _speed_profile(
    cruise_mps: float,
    brake_stations_m: list[float],
    length_m: float,
    duration_s: float,
    *,
    brake_mps2: float = BRAKE_MPS2,
    reaccelerate_mps2: float = REACCELERATE_MPS2,
) -> tuple[SpeedProfile, float]:
    """Cruise with brakings (at `brake_mps2`, then back up at `reaccelerate_mps2`: the driver's style) starting at the
    given stations; returns the profile and the duration that keeps the vehicle on the road."""
    if not (brake_mps2 > 0 and reaccelerate_mps2 > 0):
        raise ValueError(f"brake_mps2 and reaccelerate_mps2 must be > 0, got {brake_mps2!r}, {reaccelerate_mps2!r}")
    low = LOW_SPEED_SHARE * cruise_mps
    times, speeds = [0.0], [cruise_mps]
    t, s = 0.0, 0.0
    for station in sorted(brake_stations_m):
        if station <= s:
            continue
        t += (station - s) / cruise_mps
        brake_s = (cruise_mps - low) / brake_mps2
        accel_s = (cruise_mps - low) / reaccelerate_mps2
        times += [t, t + brake_s, t + brake_s + accel_s]
        speeds += [cruise_mps, low, cruise_mps]
        t += brake_s + accel_s
        s = station + (cruise_mps + low) / 2 * (brake_s + accel_s)
    end_t = t + max(0.0, length_m - ROUTE_END_MARGIN_M - s) / cruise_mps
    duration = min(duration_s, end_t)
    times.append(max(end_t, times[-1] + 1.0))
    speeds.append(cruise_mps)
    return SpeedProfile(np.array(times), np.array(speeds)), duration


def plan_fleet(
    network: Network,
    vehicles: int,
    *,
    duration_s: float = 120.0,
    seed: int = 0,
    patch_braking_share: float = 0.5,
    per_slippery_patch: int = 0,
    prefix: str = "fleet",
) -> list[VehiclePlan]:
    """Plan `vehicles` drives on the network. First `per_slippery_patch` vehicles for each patch whose adhesion is
    below SLIPPERY_MU and that a road reaches within the drive: they take such a road and brake on the patch (a demo
    that must show a warning needs two observations of one patch). The others take any road, roads crossing a
    patch twice as often (they are the interesting ones), and brake on a patch with probability
    `patch_braking_share`, elsewhere otherwise."""
    if vehicles < 1:
        raise ValueError(f"vehicles must be >= 1, got {vehicles}")
    if not 0.0 <= patch_braking_share <= 1.0:
        raise ValueError(f"patch_braking_share must be in [0, 1], got {patch_braking_share}")
    rng = np.random.default_rng(seed)
    roads = [r for road in network.roads for r in (road, road.reversed())]
    weights = np.array([2.0 if network.patch_stations(r) else 1.0 for r in roads])
    kinds = list(VEHICLES.values())
    assigned: list[tuple[Road, tuple[float, float] | None]] = []  # (road, patch stations to brake on)
    for patch in network.patches:
        if patch.mu >= SLIPPERY_MU:
            continue
        reach = [
            (r, (first, last))
            for r in roads
            for first, last, p in network.patch_stations(r)
            if p is patch and first < r.cruise_mps * duration_s * 0.8
        ]
        for k in range(per_slippery_patch if reach else 0):
            assigned.append(reach[k % len(reach)])
    while len(assigned) < vehicles:
        road = roads[rng.choice(len(roads), p=weights / weights.sum())]
        patches = network.patch_stations(road)
        if patches and rng.random() < patch_braking_share:
            first, last, _ = patches[rng.integers(len(patches))]
            assigned.append((road, (first, last)))
        else:
            assigned.append((road, None))
    plans = []
    for k, (road, patch_span) in enumerate(assigned[:vehicles]):
        cruise = road.cruise_mps * rng.uniform(0.9, 1.05)
        length = road.path.length_m
        if patch_span is not None:
            first, last = patch_span
            brakes = [first + min(10.0, (last - first) / 4)]
        else:
            brakes = sorted(rng.uniform(0.1 * length, 0.8 * length, size=rng.integers(1, 3)).tolist())
        speed, duration = _speed_profile(cruise, brakes, length, duration_s)
        vehicle = kinds[k % len(kinds)]
        vehicle_id = f"{prefix}-{k:03d}"
        scenario = Scenario(
            run_id=vehicle_id,
            path=road.path,
            mu=network.mu_profile(road),
            speed=speed,
            vehicle=vehicle,
            duration_s=max(1.0, math.floor(duration * 10) / 10),
            seed=int(rng.integers(2**31)),
            condition="fleet",
            road=road.name,
            manoeuvre="cruise-brake",
        )
        plans.append(VehiclePlan(vehicle_id, vehicle, road, scenario, tuple(brakes)))
    return plans


def planned_arrival(speed: SpeedProfile, depart_s: float = 0.0, step_s: float = 0.1):
    """The clock of a drive as planned: stations (m) -> the times (s) the speed profile reaches them, for a vehicle
    that departs at `depart_s` (for Network.mu_profile: patches that come and go). The driver tracks the profile
    closely; where ABS cannot follow a braking on ice the vehicle runs a little ahead of it."""
    end_s = float(speed.times_s[-1])
    t = np.arange(0.0, end_s + step_s, step_s)
    v = np.maximum(np.interp(t, speed.times_s, speed.speeds_mps), 1e-3)
    s = np.concatenate([[0.0], np.cumsum((v[1:] + v[:-1]) / 2 * step_s)])  # trapezoid: station(t)

    def arrival(stations_m: np.ndarray) -> np.ndarray:
        stations_m = np.asarray(stations_m, dtype=np.float64)
        beyond = np.maximum(stations_m - s[-1], 0.0) / v[-1]  # past the profile's end: at its last speed
        return depart_s + np.interp(stations_m, s, t) + beyond

    return arrival


def simulate_fleet(plans: list[VehiclePlan], network: Network) -> dict[str, list[dict]]:
    """Each vehicle's wire samples (timestamps from 0 ms: `stream` sets the clock)."""
    sensors = SensorModel(origin_lat_deg=network.origin[0], origin_lon_deg=network.origin[1])
    table = simulate([p.scenario for p in plans], sensors=sensors)
    return {
        p.vehicle_id: wire_samples(table.filter(pc.equal(table["run_id"], p.vehicle_id)), p.vehicle_id, 0)
        for p in plans
    }


def timeline(samples: dict[str, list[dict]], speed: float, now_s: float) -> list[dict]:
    """Every vehicle's samples (timestamps from 0) on one clock for `roadgrip.fleet.replay.replay` at `speed`: all
    vehicles start now, and the timestamps are shifted as the module docstring says, so that none is ever ahead of
    the clock that sends it (speed math.inf: the whole drive lies in the past)."""
    if not speed > 0:
        raise ValueError(f"speed must be > 0, got {speed}")
    longest_ms = max(run[-1]["timestamp_ms"] for run in samples.values() if run) + SAMPLE_PERIOD_MS
    start_ms = int(now_s * 1000) - int(longest_ms * (1.0 - 1.0 / speed))
    return [{**s, "timestamp_ms": start_ms + s["timestamp_ms"]} for run in samples.values() for s in run]
