"""pmf's steering-torque term (roadgrip/estimators/aligning.py): the brush model's pneumatic trail, the per-mu gain's
calibration, the likelihood it gives, pmf without the torques as before, old states, and on simulated ramp and sine
steers with the torques sent (lateral_drives.py's drives, steering_torque on): no false low on dry, ice seen."""

from __future__ import annotations

import dataclasses
import functools
from pathlib import Path

import numpy as np
import pytest
from lateral_drives import calm_drive, run_rows, scenarios
from scipy.optimize import brentq

from roadgrip.estimators import aligning as al
from roadgrip.estimators.lateral import brush_slip
from roadgrip.estimators.pmf import K_AL, MU_GRID, N_MEM, N_MEM_V2, N_MEM_V3, NM, PMFEstimator
from roadgrip.fleet.importers import get_importer
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.roads import MuProfile
from roadgrip.sim.roads import Path as RoadPath
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import PAPER_SUV, VehicleParams

TORQUES = ("steering_torque_nm", "eps_assist_torque_nm")
RATIO, T0, TM, FZ = 16.0, 0.045, 0.025, 11000.0


def test_the_trail_shrinks_as_the_brush_model_says():
    """theta = tan(alpha) / tan(alpha_sl) solves 1 - (1 - theta)^3 = u; the trail is t0 (1 - theta): about 0.79 t0 at
    half the limit, 0.59 t0 at 0.8 of it; and theta is the brush slip angle's c alpha / (3 mu) (lateral.py)."""
    for u, expected in ((0.5, 0.794), (0.8, 0.585)):
        theta = brentq(lambda th, u=u: 1.0 - (1.0 - th) ** 3 - u, 0.0, 1.0)
        assert al.trail_factor(u * 0.6, 0.6) == pytest.approx(1.0 - theta, rel=1e-9)
        assert al.trail_factor(u * 0.6, 0.6) == pytest.approx(expected, abs=1e-3)
    for f, mu, c in ((0.1, 0.3, 14.0), (-0.4, 0.9, 20.0), (0.05, 0.1, 8.0)):
        theta = c * abs(brush_slip(f, mu, c)) / (3.0 * mu)
        assert al.trail_factor(f, mu) == pytest.approx(1.0 - theta, rel=1e-9)
    assert al.trail_factor(0.7, 0.6) == 0.0


def _column(f, mu, scale, tm=TM):
    """The driver's and the EPS's torques of a front axle at force per load f on mu, the torque scale `scale`."""
    moment = (T0 * al.trail_factor(f, mu) + tm) * f * FZ
    column = scale * moment / RATIO
    return 0.3 * column, 0.7 * column


def _drive(mem, forces, mu, scale, lk_log=None, tm=TM):
    lk = np.ones(NM)
    for f in forces:
        driver, eps = _column(f, mu, scale, tm)
        spoke = al.aligning_step(
            mem, 0, driver, eps, 0.1, 0.0, f, 0.0, FZ, 0.01, RATIO, T0, TM, False, MU_GRID, 0.3, lk
        )
        if spoke and lk_log is not None:
            lk_log += np.log(lk)
    return lk_log


def _fresh():
    mem = np.zeros(al.memory_size(NM))
    al.init_aligning_memory(mem, 0, NM)
    return mem


def _gains(mem):
    return mem[al.A_CELLS :: 2]


def test_calm_driving_calibrates_the_cars_own_torque_scale():
    """A car whose torque counts are 0.6 of the nominal: after calm cornering (|f| 0.03-0.08, both ways) every
    hypothesis of mu >= 0.6 has learned the gain 0.6, whatever mu it assumes (the trail is t0 there)."""
    rng = np.random.default_rng(1)
    mem = _fresh()
    forces = rng.uniform(0.03, 0.08, 300) * rng.choice([-1.0, 1.0], 300)
    _drive(mem, forces, 0.9, 0.6)
    gains = _gains(mem)
    assert np.all(np.abs(gains[MU_GRID >= 0.6] - 0.6) < 0.03)
    assert mem[al.A_W] == pytest.approx(30.0)


def test_a_shrinking_trail_points_to_ice_and_a_full_one_to_grip():
    """After calm driving, a ramp steer: on ice (mu 0.2) the front axle's force per load rising to 0.15 (0.75 of the
    limit), the trail shrinking as the brush model's: the likelihood (tempered, 6 s) favours mu near 0.2 over dry
    asphalt's 0.9 by a factor above e^1.5. On dry asphalt (mu 0.9), f rising to 0.45 with the trail hardly
    shrinking: it favours 0.9 over 0.5, under which the same forces would bring the axle near its limit."""
    rng = np.random.default_rng(2)
    for mu, f_max, other in ((0.2, 0.15, 0.9), (0.9, 0.45, 0.5)):
        mem = _fresh()
        _drive(mem, rng.uniform(0.03, 0.05, 100) * rng.choice([-1.0, 1.0], 100), mu, 1.0)
        log = _drive(mem, np.linspace(0.05, f_max, 60), mu, 1.0, np.zeros(NM))
        i_true, i_other = np.argmin(np.abs(MU_GRID - mu)), np.argmin(np.abs(MU_GRID - other))
        assert log[i_true] - log[i_other] > 1.5
        assert abs(MU_GRID[np.argmax(log)] - mu) <= 0.1


def test_the_caster_trail_off_the_profile_does_not_read_as_ice():
    """The car's mechanical trail 40 % above its profile's (the gain absorbs the total, not the split): dry asphalt at
    f 0.2-0.4 still favours mu 0.9 over 0.45."""
    rng = np.random.default_rng(3)
    mem = _fresh()
    _drive(mem, rng.uniform(0.03, 0.06, 100) * rng.choice([-1.0, 1.0], 100), 0.9, 1.0, tm=1.4 * TM)
    log = _drive(mem, rng.uniform(0.2, 0.4, 50), 0.9, 1.0, np.zeros(NM), tm=1.4 * TM)
    assert log[np.argmin(np.abs(MU_GRID - 0.9))] > log[np.argmin(np.abs(MU_GRID - 0.45))]


def test_a_controller_or_a_small_force_says_nothing():
    mem = _fresh()
    lk = np.ones(NM)
    args = (0.0, 0.2, 0.0, FZ, 0.01, RATIO, T0, TM)
    assert not al.aligning_step(mem, 0, 1.0, 2.0, 0.1, *args, True, MU_GRID, 0.3, lk)  # ABS, ESC or a wheel past
    assert not al.aligning_step(mem, 0, 0.1, 0.1, 0.1, 0.0, 0.02, 0.0, FZ, 0.01, RATIO, T0, TM, False, MU_GRID, 0.3, lk)
    fresh = _fresh()
    fresh[al.A_F_PREV] = 0.02
    assert np.array_equal(mem, fresh)


@functools.cache
def _drives(calibrated: bool):
    """lateral_drives' test split with the steering torques sent: per run, the truth and pmf's estimates with the
    torques and without them (after the calm drive where `calibrated`)."""
    runs = [s.replace(effects=dataclasses.replace(s.effects, steering_torque=True)) for s in scenarios("test")]
    return _with_and_without_torques(runs, calibrated)


def _with_and_without_torques(runs, calibrated: bool):
    """Per run (torques sent): the truth and pmf's estimates with the torques and without them, after the run's calm
    drive where `calibrated` (a segment of its own: the grid restarts, the calibration carries on)."""
    table = simulate(runs + ([calm_drive(s) for s in runs] if calibrated else []))
    estimator = PMFEstimator()
    out = {}
    for scenario in runs:
        run, rows, segments = run_rows(table, scenario.run_id, calibrated)
        mu = run["mu"].to_numpy()
        res = {"mu_true": mu, "u_lat": np.abs(run["ay_true_mps2"].to_numpy()) / (mu * G_MPS2)}
        for name, tab in (("torques", rows), ("base", rows.drop_columns(list(TORQUES)))):
            est = estimator.estimate_batch(tab, segments, scenario.vehicle).slice(rows.num_rows - run.num_rows)
            res[name] = {k: est[k].to_numpy() for k in ("mu", "mu_lower", "mu_upper")}
        out[scenario.run_id] = res
    return out


@pytest.mark.slow
@pytest.mark.parametrize("calibrated", [False, True])
def test_a_dry_steer_with_torques_is_never_called_slippery(calibrated):
    """Dry asphalt (mu 0.9), ramp and sine steers to past the limit, two vehicles, Dugoff and Magic Formula tires at
    0.8 and 1.2 x the profile's stiffness: with the torques, mu_upper never falls below 0.4."""
    for run_id, r in _drives(calibrated).items():
        if r["mu_true"][0] > 0.5:
            assert r["torques"]["mu_upper"].min() >= 0.4, run_id


@pytest.mark.slow
def test_an_ice_ramp_steer_is_seen_by_the_understeer_angle_and_more_so_with_torques():
    """A car fresh on the road (no calm driving: its tires' compliances at a new car's prior) in a ramp steer on ice
    (mu 0.15, 0.2) to past the limit. Where the front axle works at 0.8 of the limit and more, the understeer term
    (the compliances a state its samples share, docs/ESTIMATORS.md 11) reads the bend: the median estimate is below
    0.45 without the torques (before that term spoke from the first sample, the prior's median: above 0.6), and with
    them too, their mean mu_upper below the one without (the medians may both sit at the grid's cell above the truth),
    the truth inside the interval on at least 90 % of the samples.
    (Not met: mu_upper below 0.45 before the bend, docs/ESTIMATORS.md 9.)"""
    for run_id, r in _drives(False).items():
        if r["mu_true"][0] < 0.5 and run_id.startswith("ramp"):
            hard = r["u_lat"] >= 0.8
            t, b = r["torques"], r["base"]
            assert np.median(b["mu"][hard]) < 0.45, run_id
            assert np.median(t["mu"][hard]) < 0.45, run_id
            assert t["mu_upper"][hard].mean() < b["mu_upper"][hard].mean(), run_id
            covered = (t["mu_lower"] <= r["mu_true"]) & (r["mu_true"] <= t["mu_upper"])
            assert covered.mean() >= 0.9, run_id


@functools.cache
def _walking_pace_turns():
    """A turn of radius 22 m at walking pace, 2 m/s rising to 0.95 of an icy road's limit (mu 0.1: 4.5 m/s, under pmf's
    slip speed of 5 m/s, where neither the slip terms nor the understeer angle speak) and the same speeds on dry asphalt
    (0.9), by lateral_drives' two test cars on their two tires, torques sent, after the calm drive: per run, the truth
    and pmf's estimates with and without the torques."""
    radius = 22.0
    v_end = np.sqrt(0.95 * 0.1 * G_MPS2 * radius)
    cars = {}  # the first of lateral_drives' test runs for each of its two cars on each of its two tires
    for s in scenarios("test"):
        cars.setdefault((s.vehicle.name, type(s.tire).__name__), s)
    runs = []
    for s in cars.values():
        for mu in (0.1, 0.9):
            runs.append(
                s.replace(
                    run_id=f"walk-{s.run_id}-{mu}",
                    path=RoadPath.circle(radius, 400.0),
                    mu=MuProfile.uniform(mu),
                    speed=SpeedProfile([0.0, 12.0, 20.0], [2.0, v_end, v_end]),
                    steer=None,
                    duration_s=20.0,
                    effects=dataclasses.replace(s.effects, steering_torque=True),
                )
            )
    return _with_and_without_torques(runs, True)


@pytest.mark.slow
def test_a_turn_on_ice_at_walking_pace_is_read_through_the_torques():
    """Below the slip speed only the steering torques speak of the front axle (pmf's ALIGNING_MIN_SPEED_MPS, 2 m/s):
    a car that has calibrated its trail in calm driving reads the trail's collapse where the front axle works at 0.8
    of the icy road's limit and more (median below 0.3; without the torques the prior's 0.75 stays), the truth inside
    the interval on at least 90 % of the samples; on dry asphalt at the same speeds mu_upper never falls below 0.4."""
    for run_id, r in _walking_pace_turns().items():
        t, b = r["torques"], r["base"]
        if r["mu_true"][0] < 0.5:
            hard = r["u_lat"] >= 0.8
            assert hard.sum() >= 50, run_id
            assert np.median(t["mu"][hard]) < 0.3, run_id
            assert t["mu_upper"][hard].mean() < b["mu_upper"][hard].mean(), run_id
            covered = (t["mu_lower"] <= r["mu_true"]) & (r["mu_true"] <= t["mu_upper"])
            assert covered.mean() >= 0.9, run_id
        else:
            assert t["mu_upper"].min() >= 0.4, run_id


def test_without_the_torques_pmf_is_as_before():
    """Torques null on the wire, or absent from the table: the same estimates, and the block untouched."""
    scenario = scenarios("test")[0]
    scenario = scenario.replace(effects=dataclasses.replace(scenario.effects, steering_torque=False), duration_s=16.0)
    table = simulate([scenario])
    assert all(np.isnan(table[c].to_numpy(zero_copy_only=False)).all() for c in TORQUES)
    segments = np.zeros(table.num_rows, dtype=np.int64)
    estimator = PMFEstimator()
    absent = estimator.estimate_batch(table.drop_columns(list(TORQUES)), segments, scenario.vehicle)
    null = estimator.estimate_batch(table, segments, scenario.vehicle)
    assert absent.equals(null)
    state = estimator.start(scenario.vehicle)
    fresh = state.mem[K_AL:N_MEM_V3].copy()
    for row in table.to_pylist():
        estimator.update(state, row)
    assert np.array_equal(state.mem[K_AL:N_MEM_V3], fresh)


def test_a_state_saved_before_the_torque_block_loads():
    """A checkpoint of the previous layout (N_MEM_V2 numbers): everything kept, the block fresh."""
    estimator = PMFEstimator()
    state = estimator.start(PAPER_SUV)
    state.mem[: N_MEM_V2 - 1] += 0.5
    saved = estimator.state_to_dict(state)
    saved["memory"] = saved["memory"][:N_MEM_V2]
    loaded = estimator.state_from_dict(saved)
    assert loaded.mem.size == N_MEM
    assert np.array_equal(loaded.mem[:N_MEM_V2], state.mem[:N_MEM_V2])
    fresh = estimator.start(PAPER_SUV).mem  # the block and those appended after it, as a new car holds them
    assert np.array_equal(loaded.mem[K_AL:], fresh[K_AL:])


def test_the_profile_carries_the_trails_and_old_profiles_load():
    d = PAPER_SUV.to_dict()
    assert d["mechanical_trail_m"] == 0.025 and d["tire_front"]["pneumatic_trail_m"] == 0.045
    del d["mechanical_trail_m"], d["tire_front"]["pneumatic_trail_m"]
    old = VehicleParams.from_dict(d)
    assert old.mechanical_trail_m == 0.025 and old.tire_front.pneumatic_trail_m == 0.04
    with pytest.raises(ValueError, match="mechanical_trail_m"):
        PAPER_SUV.replace(mechanical_trail_m=-0.01)


def test_the_rav4_street_drive_with_its_torques_gives_no_alarm():
    """The RAV4's street drive carries STEER_TORQUE_SENSOR (driver and EPS, the nominal 0.01 N m a count): the term
    reads it (its calibration sees the drive's few seconds of cornering above |f| = 0.03) and no mu_upper falls below
    0.4. The drive is calm (|a_y| under 0.56 m/s^2 on 99 % of it): the trail barely speaks, the scale is the car's."""
    importer = get_importer("can-dbc")
    log = Path(__file__).parents[2] / "data/real/toyota_rav4_street"
    table, vehicle = importer.load(log), importer.profile(log)
    estimator = PMFEstimator()
    state = estimator.start(vehicle)
    uppers = [e.mu_upper for e in (estimator.update(state, row) for row in table.to_pylist()) if e is not None]
    assert len(uppers) > 900 and min(uppers) >= 0.4
    assert state.mem[K_AL + al.A_W] > 1.0
