"""Road grade in the body dynamics, and the traction/stability-control flags of the integrator.

On a grade the weight's component along the road, -g sin(grade), enters dv/dt; the accelerometer (the specific force of
the tire and drag forces, `ax_mps2`) does not see it, and the loads carry m g cos(grade)."""

import math

import numpy as np
import pytest

from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.integrator import CHANNELS, run_batch
from roadgrip.sim.roads import GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import SAMPLE_PERIOD_S, Scenario, pack
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV

CH = {name: i for i, name in enumerate(CHANNELS)}
GRADE_RAD = 0.06
RUNS = [
    # no tire force (mu 0): the car coasts down a 6 % slope
    Scenario(
        "downhill-ice",
        Path.straight(800.0),
        MuProfile.uniform(0.0),
        SpeedProfile([0.0], [10.0]),
        grade=GradeProfile.uniform(-GRADE_RAD),
        duration_s=6.0,
    ),
    # steady 15 m/s up a 6 % slope on a dry road: the tires push m g sin(grade) + drag
    Scenario(
        "uphill-steady",
        Path.straight(800.0),
        MuProfile.uniform(0.9),
        SpeedProfile([0.0], [15.0]),
        grade=GradeProfile.uniform(GRADE_RAD),
        duration_s=8.0,
    ),
    # the same on a level road
    Scenario("level-steady", Path.straight(800.0), MuProfile.uniform(0.9), SpeedProfile([0.0], [15.0]), duration_s=8.0),
    # a hard start on ice: the driven wheels spin and traction control cuts the torque
    Scenario(
        "ice-start",
        Path.straight(800.0),
        MuProfile.uniform(0.1),
        SpeedProfile([0.0, 10.0], [0.0, 20.0]),
        vehicle=MIDSIZE_SEDAN,
        duration_s=6.0,
    ),
]


@pytest.fixture(scope="module")
def runs():
    out = run_batch(pack(RUNS), max(s.n_samples for s in RUNS), SAMPLE_PERIOD_S)
    return {s.run_id: out[k] for k, s in enumerate(RUNS)}


def test_coasting_downhill_accelerates_at_g_sin_grade_and_the_accelerometer_reads_drag_only(runs):
    out = runs["downhill-ice"]
    vx, ax = out[:, CH["vx_mps"]], out[:, CH["ax_mps2"]]
    dvdt = np.diff(vx) / SAMPLE_PERIOD_S
    assert dvdt[5:] == pytest.approx(G_MPS2 * math.sin(GRADE_RAD) + ax[6:], abs=1e-3)
    assert np.abs(ax).max() < 0.06, "no tire force: the accelerometer reads only the drag"
    assert np.abs(out[:, [CH[f"fx_{w}_n"] for w in ("fl", "fr", "rl", "rr")]]).max() == 0.0
    assert (out[:, CH["grade_rad"]] == -GRADE_RAD).all()


def test_loads_carry_the_normal_component_of_the_weight(runs):
    out = runs["downhill-ice"]
    fz = out[20:, [CH[f"fz_{w}_n"] for w in ("fl", "fr", "rl", "rr")]].sum(axis=1)
    assert fz == pytest.approx(PAPER_SUV.mass_kg * G_MPS2 * math.cos(GRADE_RAD), rel=1e-3)


def test_steady_climb_needs_the_weights_component_and_the_accelerometer_reads_it(runs):
    up, level = runs["uphill-steady"], runs["level-steady"]
    assert up[-20:, CH["vx_mps"]] == pytest.approx(15.0, abs=0.05), "the driver holds the speed up the slope"
    fx_up = up[-20:, [CH[f"fx_{w}_n"] for w in ("fl", "fr", "rl", "rr")]].sum(axis=1)
    fx_level = level[-20:, [CH[f"fx_{w}_n"] for w in ("fl", "fr", "rl", "rr")]].sum(axis=1)
    assert (fx_up - fx_level).mean() == pytest.approx(PAPER_SUV.mass_kg * G_MPS2 * math.sin(GRADE_RAD), rel=0.02)
    assert (up[-20:, CH["ax_mps2"]] - level[-20:, CH["ax_mps2"]]).mean() == pytest.approx(
        G_MPS2 * math.sin(GRADE_RAD), rel=0.02
    )


def test_a_level_road_is_a_flat_grade_profile():
    assert GradeProfile.flat().is_flat and not GradeProfile.uniform(0.01).is_flat
    assert GradeProfile([0.0, 100.0], [0.0, 0.04]).at([50.0, 200.0]) == pytest.approx([0.02, 0.04])
    with pytest.raises(ValueError, match=r"GradeProfile.grade_rad must lie in \[-0.3, 0.3\], got 0.5"):
        GradeProfile.uniform(0.5)
    with pytest.raises(TypeError, match="Scenario.grade must be a GradeProfile"):
        Scenario("x", Path.straight(100.0), MuProfile.uniform(0.5), SpeedProfile([0.0], [5.0]), grade=0.02)


def test_traction_control_flag_marks_its_cuts_and_only_them(runs):
    start, steady = runs["ice-start"], runs["level-steady"]
    assert start[:, CH["tcs_active"]].any(), "spinning driven wheels on ice: traction control intervenes"
    assert not steady[:, CH["tcs_active"]].any() and not steady[:, CH["esc_active"]].any()
    assert not start[:, CH["esc_active"]].any(), "straight ahead: no sideslip, no ESC"
    # at t = 0 the car stands at a zero reference speed: the driver holds it on the brake
    assert not start[1:, CH["brake_active"]].any() and not steady[:, CH["brake_active"]].any()


def test_the_dataset_carries_the_tcs_and_esc_flags():
    from roadgrip.sim.simulate import simulate

    table = simulate([RUNS[3]])
    assert table["tcs_active"].to_numpy().any() and not table["esc_active"].to_numpy().any()
    assert table.schema.field("tcs_active").nullable, "optional in wire format v1"
