"""The stability control's trigger: the body's sideslip beyond the kinematic one, so a slow tight turn is no skid.

In a turn of radius R at walking pace the rear axle rolls without a slip angle and the CoG's sideslip is
atan(l_r / R), about 8 degrees at R = 10 m: a raw sideslip threshold of 3 degrees fired ESC there and cut the drive
torque (the car slowed from 4 to 1.5 m/s, and pmf read the flag as a car at its limit on a dry road)."""

import math

import numpy as np
import pytest

from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.integrator import CHANNELS, run_batch
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import SAMPLE_PERIOD_S, Scenario, pack
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV

CH = {name: i for i, name in enumerate(CHANNELS)}
RUNS = [
    # a dry 10 m radius turn at 4 m/s: large kinematic sideslip, no skid
    Scenario(
        "dry-tight-turn",
        Path.circle(10.0, 200.0),
        MuProfile.uniform(0.9),
        SpeedProfile([0.0], [4.0]),
        vehicle=PAPER_SUV,
        duration_s=15.0,
    ),
    # a sine steer on ice at 20 m/s asking several times the road's friction: the car skids
    Scenario(
        "ice-skid",
        Path.straight(600.0),
        MuProfile.uniform(0.1),
        SpeedProfile([0.0], [20.0]),
        vehicle=MIDSIZE_SEDAN,
        steer=SteerInput(1.0, 10.0, 0.1, 0.5),
        duration_s=10.0,
    ),
]


@pytest.fixture(scope="module")
def runs():
    out = run_batch(pack(RUNS), max(s.n_samples for s in RUNS), SAMPLE_PERIOD_S)
    return {s.run_id: out[k] for k, s in enumerate(RUNS)}


def test_a_slow_dry_tight_turn_has_kinematic_sideslip_and_no_esc(runs):
    out = runs["dry-tight-turn"][30:]
    vx, vy, r = out[:, CH["vx_mps"]], out[:, CH["vy_mps"]], out[:, CH["yaw_rate_radps"]]
    sideslip = np.degrees(np.arctan2(vy, vx))
    kinematic = np.degrees(np.arctan2(PAPER_SUV.cg_to_rear_axle_m * r, vx))
    assert np.abs(sideslip).min() > 3.0, "the raw sideslip is beyond the old 3-degree threshold"
    assert np.abs(sideslip - kinematic).max() < 1.0, "no skid: the sideslip is the kinematic one"
    assert not runs["dry-tight-turn"][:, CH["esc_active"]].any()
    assert vx == pytest.approx(4.0, abs=0.15), "no torque cut: the driver holds the speed"


def test_a_skid_on_ice_sets_the_esc_flag(runs):
    out = runs["ice-skid"]
    vx, vy, r = out[:, CH["vx_mps"]], out[:, CH["vy_mps"]], out[:, CH["yaw_rate_radps"]]
    excess = np.arctan2(vy, vx) - np.arctan2(MIDSIZE_SEDAN.cg_to_rear_axle_m * r, vx)
    assert np.abs(excess).max() > math.radians(10.0), "the rear slides"
    assert out[:, CH["esc_active"]].any()
    first = int(np.argmax(np.abs(excess) > math.radians(3.0)))
    assert out[first : first + 3, CH["esc_active"]].any(), "the flag follows the skid within 0.3 s"
