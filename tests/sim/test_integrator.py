"""The compiled simulator against closed forms and limits: free rolling at v / R, the linear bicycle model's steady
yaw-rate gain, braking at mu g with ABS and locked wheels without, the friction limit, determinism, and mu steps along
the road.

Runs are short and batched (one `run_batch` call per fixture) to keep the suite fast."""

import numpy as np
import pytest

from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.integrator import CHANNELS, run_batch
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import SAMPLE_PERIOD_S, Scenario, pack
from roadgrip.units import G_MPS2, kmh_to_mps
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires import BurckhardtTire, DugoffTire, MagicFormulaTire

CH = {name: i for i, name in enumerate(CHANNELS)}
WHEELS = ("fl", "fr", "rl", "rr")
VEHICLES = (PAPER_SUV, MIDSIZE_SEDAN)
TIRES = (DugoffTire(), MagicFormulaTire(), BurckhardtTire())


def simulate(scenarios):
    """Recorded channels of a batch, shape (runs, samples, channels), sampled every SAMPLE_PERIOD_S."""
    n_samples = max(s.n_samples for s in scenarios)
    return run_batch(pack(scenarios), n_samples, SAMPLE_PERIOD_S)


def ch(out, name):
    return out[..., CH[name]]


def per_wheel(out, template):
    """A per-wheel channel from a template like 'slip_ratio_{}'; shape (..., 4), wheels in fl, fr, rl, rr order."""
    return out[..., [CH[template.format(w)] for w in WHEELS]]


def understeer_gradient(v):
    """K = m (l_r C_r - l_f C_f) / (L^2 C_f C_r) [s^2/m^2], C_f, C_r axle cornering stiffnesses at the static loads."""
    front_axle_n, rear_axle_n = v.static_axle_loads_n
    c_f = 2.0 * v.tire_front.cornering_stiffness_per_load_per_rad * front_axle_n / 2.0  # two wheels, each half the axle
    c_r = 2.0 * v.tire_rear.cornering_stiffness_per_load_per_rad * rear_axle_n / 2.0
    lf, lr, length = v.cg_to_front_axle_m, v.cg_to_rear_axle_m, v.wheelbase_m
    return v.mass_kg * (lr * c_r - lf * c_f) / (length**2 * c_f * c_r)


def yaw_rate_gain(v, speed_mps):
    """Steady-state r / delta of the linear bicycle model: (v / L) / (1 + K v^2)."""
    return (speed_mps / v.wheelbase_m) / (1.0 + understeer_gradient(v) * speed_mps**2)


# --- free rolling ---------------------------------------------------------------------------------------------------

CRUISE_SPEEDS_MPS = (10.0, 30.0)
CRUISE = [
    Scenario(
        f"cruise-{v.name}-{t.name}-{speed:.0f}",
        Path.straight(500.0),
        MuProfile.uniform(0.8),
        SpeedProfile([0.0], [speed]),
        vehicle=v,
        tire=t,
        duration_s=6.0,
    )
    for v in VEHICLES
    for t in TIRES
    for speed in CRUISE_SPEEDS_MPS
]


@pytest.fixture(scope="module")
def cruise_runs():
    return simulate(CRUISE)


@pytest.mark.parametrize("k", range(len(CRUISE)), ids=[s.run_id for s in CRUISE])
def test_free_rolling_wheels_turn_at_v_over_r(cruise_runs, k):
    scenario, out = CRUISE[k], cruise_runs[k]
    late = ch(out, "t_s") >= 3.0  # long after the initial condition omega = v / R
    vx = ch(out, "vx_mps")[late]
    omega = per_wheel(out, "omega_{}_radps")[late]
    expected = vx / scenario.vehicle.wheel_radius_m
    np.testing.assert_allclose(omega, np.repeat(expected[:, None], 4, axis=1), rtol=0.005)
    # and the car holds its constant speed on the straight road, without turning
    assert vx == pytest.approx(scenario.speed.speeds_mps[0], rel=0.005)
    assert np.abs(ch(out, "yaw_rate_radps")).max() < 1e-9
    assert np.abs(ch(out, "y_m")).max() < 1e-6


# --- steady cornering: the linear bicycle model -----------------------------------------------------------------------

CORNER_SPEED_MPS = 20.0
CORNER_AY_MPS2 = 0.1 * G_MPS2


def corner_steer_rad(v):
    """Road-wheel angle that gives about 0.1 g at 20 m/s by the linear model: r = a_y / v = gain delta."""
    return CORNER_AY_MPS2 / CORNER_SPEED_MPS / yaw_rate_gain(v, CORNER_SPEED_MPS)


CORNERING = [
    Scenario(
        f"corner-{v.name}-{t.name}",
        Path.straight(1000.0),
        MuProfile.uniform(0.9),
        SpeedProfile([0.0], [CORNER_SPEED_MPS]),
        vehicle=v,
        tire=t,
        steer=SteerInput.constant(corner_steer_rad(v)),
        duration_s=15.0,
    )
    for v in VEHICLES
    for t in (DugoffTire(), MagicFormulaTire())
]


@pytest.fixture(scope="module")
def cornering_runs():
    return simulate(CORNERING)


@pytest.mark.parametrize("k", range(len(CORNERING)), ids=[s.run_id for s in CORNERING])
def test_steady_cornering_matches_the_linear_bicycle_yaw_rate_gain(cornering_runs, k):
    scenario, out = CORNERING[k], cornering_runs[k]
    v = scenario.vehicle
    steady = ch(out, "t_s") >= 12.0
    vx = ch(out, "vx_mps")[steady].mean()
    delta = ch(out, "steer_rad")[steady].mean()
    yaw_rate = ch(out, "yaw_rate_radps")[steady]
    ay = ch(out, "ay_mps2")[steady].mean()
    # settled, and in the linear range the test is about
    assert np.ptp(yaw_rate) < 1e-3 * abs(yaw_rate.mean())
    assert ay == pytest.approx(CORNER_AY_MPS2, rel=0.2)
    assert delta == pytest.approx(scenario.steer.amplitude_rad, rel=1e-3)
    assert yaw_rate.mean() / delta == pytest.approx(yaw_rate_gain(v, vx), rel=0.05)


@pytest.mark.parametrize("k", range(len(CORNERING)), ids=[s.run_id for s in CORNERING])
def test_steady_cornering_rolls_by_the_roll_stiffness(cornering_runs, k):
    """Steady roll: (K_f + K_r) phi = m_s e (a_y + g sin phi), e the CoG height over the roll axis; positive (right side
    down) in a left turn."""
    scenario, out = CORNERING[k], cornering_runs[k]
    v = scenario.vehicle
    steady = ch(out, "t_s") >= 12.0
    ay = ch(out, "ay_mps2")[steady].mean()
    h_ra = (v.roll_center_height_front_m * v.cg_to_rear_axle_m + v.roll_center_height_rear_m * v.cg_to_front_axle_m) / (
        v.wheelbase_m
    )
    e = v.cg_height_m - h_ra
    k_total = v.roll_stiffness_front_nmprad + v.roll_stiffness_rear_nmprad
    expected = v.sprung_mass_kg * e * ay / (k_total - v.sprung_mass_kg * G_MPS2 * e)  # small angle
    assert ch(out, "roll_rad")[steady].mean() == pytest.approx(expected, rel=0.01)
    # the outer (right) wheels carry more, and the four loads still carry the weight
    fz = per_wheel(out, "fz_{}_n")[steady]
    assert (fz[:, 1] > fz[:, 0]).all() and (fz[:, 3] > fz[:, 2]).all()
    assert fz.sum(axis=1) == pytest.approx(v.mass_kg * G_MPS2, rel=1e-9)


# --- hardest braking ------------------------------------------------------------------------------------------------

BRAKE_MUS = (0.3, 0.6, 0.9)
# 25 m/s to 0 in 0.3 s (8.5 g): the driver floors the brake pedal (a 1.2 g demand), far beyond mu g
HARD_STOP = SpeedProfile([0.0, 1.0, 1.3, 10.0], [25.0, 25.0, 0.0, 0.0])
BRAKING = [
    Scenario(
        f"brake-mu{mu}-{'abs' if abs_on else 'no-abs'}",
        Path.straight(500.0),
        MuProfile.uniform(mu),
        HARD_STOP,
        abs_enabled=abs_on,
        duration_s=12.0,
    )
    for mu in BRAKE_MUS
    for abs_on in (True, False)
]


@pytest.fixture(scope="module")
def braking_runs():
    return {s.run_id: out for s, out in zip(BRAKING, simulate(BRAKING))}


def braking_window(out, high_mps=20.0, low_mps=5.0):
    """Samples after the brakes came on (t > 1 s) with the speed between low and high."""
    vx = ch(out, "vx_mps")
    return (ch(out, "t_s") > 1.0) & (vx < high_mps) & (vx > low_mps)


@pytest.mark.parametrize("mu", BRAKE_MUS)
def test_abs_braking_decelerates_at_about_mu_g(braking_runs, mu):
    """With the demand above the friction limit, ABS keeps the tires near their best: mean a_x within 10 % of mu g."""
    out = braking_runs[f"brake-mu{mu}-abs"]
    window = braking_window(out)
    assert window.sum() >= 10
    mean_ax = ch(out, "ax_mps2")[window].mean()
    ratio = -mean_ax / (mu * G_MPS2)
    assert ratio == pytest.approx(1.0, rel=0.10), f"mean a_x {mean_ax:.3f} m/s^2 is {ratio:.3f} mu g"


@pytest.mark.parametrize("mu", BRAKE_MUS)
def test_abs_is_active_while_braking_and_not_before(braking_runs, mu):
    out = braking_runs[f"brake-mu{mu}-abs"]
    abs_active = ch(out, "abs_active")
    assert set(np.unique(abs_active)) <= {0.0, 1.0}
    assert abs_active[braking_window(out)].mean() > 0.8
    assert not abs_active[ch(out, "t_s") < 1.0].any()
    # the wheels are kept rolling: slip well away from -1
    assert per_wheel(out, "slip_ratio_{}")[braking_window(out)].min() > -0.5


@pytest.mark.parametrize("mu", BRAKE_MUS)
def test_wheels_lock_without_abs(braking_runs, mu):
    out = braking_runs[f"brake-mu{mu}-no-abs"]
    window = braking_window(out, high_mps=20.0, low_mps=10.0)  # demand far above the friction limit all along
    assert window.sum() >= 5
    assert (per_wheel(out, "slip_ratio_{}")[window] < -0.95).all()
    assert (per_wheel(out, "omega_{}_radps")[window] < 1.0).all()
    assert not ch(out, "abs_active").any()


@pytest.mark.parametrize("mu", BRAKE_MUS)
def test_braking_stops_the_car(braking_runs, mu):
    for abs_on in ("abs", "no-abs"):
        out = braking_runs[f"brake-mu{mu}-{abs_on}"]
        assert ch(out, "vx_mps")[-1] == pytest.approx(0.0, abs=0.05)
        assert np.isfinite(out).all()


# --- at the friction limit --------------------------------------------------------------------------------------------

TOP_SPEED_MPS = kmh_to_mps(120.0)
LIMIT = [
    Scenario(
        f"limit-accel-{t.name}",
        Path.straight(2000.0),
        MuProfile.uniform(0.1),
        SpeedProfile.accelerate_decelerate(TOP_SPEED_MPS, 20.0, 40.0),
        tire=t,
        duration_s=40.0,
    )
    for t in TIRES
] + [
    Scenario(
        f"limit-circle-{t.name}",
        Path.circle(100.0, 1500.0),
        MuProfile.uniform(0.8),
        SpeedProfile([0.0], [35.0]),
        tire=t,
        duration_s=20.0,
    )
    for t in TIRES
]


@pytest.fixture(scope="module")
def limit_runs():
    return simulate(LIMIT)


@pytest.mark.parametrize("k", range(len(LIMIT)), ids=[s.run_id for s in LIMIT])
def test_at_the_friction_limit_the_car_slides_instead_of_blowing_up(limit_runs, k):
    """0 - 120 - 0 km/h in 40 s asks 1.7 m/s^2 of a mu 0.1 road (0.98 m/s^2); 35 m/s on a 100 m circle asks 1.25 g of a
    mu 0.8 road. The run stays finite, every tire force stays inside its friction circle, and the car falls behind its
    speed profile."""
    scenario, out = LIMIT[k], limit_runs[k]
    assert np.isfinite(out).all()
    assert np.abs(ch(out, "vx_mps")).max() < 40.0
    force = np.hypot(per_wheel(out, "fx_{}_n"), per_wheel(out, "fy_{}_n"))
    assert (force <= per_wheel(out, "mu_{}") * per_wheel(out, "fz_{}_n") * (1 + 1e-9) + 1e-6).all()
    speed_error = ch(out, "v_ref_mps") - ch(out, "vx_mps")
    assert np.abs(speed_error).max() > 5.0
    if scenario.run_id.startswith("limit-accel"):
        assert ch(out, "vx_mps").max() < 0.75 * TOP_SPEED_MPS
        ax = ch(out, "ax_mps2")
        v = scenario.vehicle
        drag = 0.5 * 1.225 * v.drag_coefficient * v.frontal_area_m2 * ch(out, "vx_mps") ** 2
        assert (np.abs(ax) <= 0.1 * G_MPS2 * 1.001 + drag / scenario.vehicle.mass_kg).all()
    else:
        assert np.abs(ch(out, "ay_mps2")).max() <= 0.8 * G_MPS2 * 1.001


# --- mu along the road ------------------------------------------------------------------------------------------------

STEP_MUS = (0.9, 0.5, 0.2)
SECTION_M = 100.0
SPLIT = MuProfile([0.0, 150.0], [0.9, 0.3], [0.6, 0.3])
MU_ROADS = [
    Scenario(
        "mu-sections",
        Path.straight(1000.0),
        MuProfile.sections(STEP_MUS, SECTION_M),
        SpeedProfile([0.0], [20.0]),
        duration_s=16.0,
    ),
    Scenario("mu-split", Path.straight(1000.0), SPLIT, SpeedProfile([0.0], [20.0]), duration_s=16.0),
]


@pytest.fixture(scope="module")
def mu_runs():
    return simulate(MU_ROADS)


def test_mu_steps_appear_at_their_stations(mu_runs):
    out = mu_runs[0]
    v = PAPER_SUV
    station = ch(out, "station_m")
    np.testing.assert_allclose(station, ch(out, "x_m"), atol=1e-6)  # a straight road along x
    assert station[-1] > 2 * SECTION_M + 10.0

    def expected(s):
        return np.select([s < SECTION_M, s < 2 * SECTION_M], STEP_MUS[:2], STEP_MUS[2])

    np.testing.assert_array_equal(ch(out, "mu"), expected(station))
    # each wheel reads the road under it: front axle l_f ahead of the CoG, rear axle l_r behind
    mu_w = per_wheel(out, "mu_{}")
    for i in (0, 1):
        np.testing.assert_array_equal(mu_w[:, i], expected(station + v.cg_to_front_axle_m))
    for i in (2, 3):
        np.testing.assert_array_equal(mu_w[:, i], expected(station - v.cg_to_rear_axle_m))
    # the first sample on the second section lies within one sample's travel of the step
    first = np.argmax(ch(out, "mu") == STEP_MUS[1])
    assert SECTION_M <= station[first] < SECTION_M + 20.0 * SAMPLE_PERIOD_S + 0.1
    assert ch(out, "t_s")[first] == pytest.approx(SECTION_M / 20.0, abs=SAMPLE_PERIOD_S + 1e-9)


def test_left_and_right_tracks_are_read_separately(mu_runs):
    out = mu_runs[1]
    station = ch(out, "station_m")
    mu_w = per_wheel(out, "mu_{}")
    front = station + PAPER_SUV.cg_to_front_axle_m
    rear = station - PAPER_SUV.cg_to_rear_axle_m
    np.testing.assert_array_equal(mu_w[:, 0], np.where(front < 150.0, 0.9, 0.3))  # left track
    np.testing.assert_array_equal(mu_w[:, 1], np.where(front < 150.0, 0.6, 0.3))  # right track
    np.testing.assert_array_equal(mu_w[:, 2], np.where(rear < 150.0, 0.9, 0.3))
    np.testing.assert_array_equal(mu_w[:, 3], np.where(rear < 150.0, 0.6, 0.3))
    # the recorded road mu is the mean of the two tracks
    np.testing.assert_allclose(ch(out, "mu"), np.where(station < 150.0, 0.75, 0.3), rtol=1e-12)


# --- determinism ------------------------------------------------------------------------------------------------------

MIXED = [BRAKING[0], BRAKING[5], CORNERING[1], LIMIT[1], LIMIT[5], MU_ROADS[0], CRUISE[3]]


def test_same_scenarios_give_bit_identical_runs():
    first = simulate(MIXED)
    second = simulate(MIXED)
    assert np.array_equal(first, second)


def test_a_run_does_not_depend_on_its_batch():
    """Runs never mix: each run alone gives exactly its rows of the batch (padding of the tables included)."""
    batch = simulate(MIXED)
    for k, scenario in enumerate(MIXED):
        alone = simulate([scenario])[0]
        n = alone.shape[0]
        assert np.array_equal(alone, batch[k, :n])
