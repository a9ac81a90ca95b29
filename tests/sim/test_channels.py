"""The optional channels (roadgrip/sim/channels.py): off they are null, on they leave every base signal as it was, and
each follows its error model (GNSS speed against the true ground speed, forces against the tire forces, the steering
torques against the brush model's aligning moment)."""

import dataclasses

import numpy as np
import pytest

from roadgrip.data.schema import CHANNEL_NAMES, TELEMETRY_COLUMNS
from roadgrip.sim.channels import ChannelModel, brush_trail_m, cornering_stiffness_per_load, optional_channels
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.scenario import SAMPLE_PERIOD_S
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import MIDSIZE_SEDAN
from roadgrip.vehicle.tires.burckhardt import BurckhardtTire
from roadgrip.vehicle.tires.dugoff import DugoffTire
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire
from tests.sim.test_production import DRIVE

WHEELS = ("fl", "fr", "rl", "rr")
PRODUCTION = ProductionEffects.production()


def columns(table):
    return {n: table[n].to_numpy(zero_copy_only=False) for n in table.column_names if n not in ("vehicle_id", "run_id")}


def sedan_channels(truth, seed=0, gnss=False, forces=False, steering=False, **kw):
    """optional_channels of the midsize sedan on a hand-made truth (only the named channels on)."""
    rng = np.random.default_rng(seed)
    return optional_channels(
        truth, MIDSIZE_SEDAN, SAMPLE_PERIOD_S, rng, gnss=gnss, forces=forces, steering=steering, **kw
    )


@pytest.fixture(scope="module")
def runs():
    base = columns(simulate([DRIVE.replace(effects=PRODUCTION)]))
    sent = columns(simulate([DRIVE.replace(effects=PRODUCTION.with_channels())]))
    return base, sent


def test_channels_off_are_null_and_on_leave_the_base_signals_bit_for_bit(runs):
    base, sent = runs
    for name in CHANNEL_NAMES:
        assert np.isnan(base[name].astype(float)).all(), name
    assert np.isfinite(sent["drive_force_n"].astype(float)).all()
    for name in TELEMETRY_COLUMNS:
        if name not in CHANNEL_NAMES and name in base:
            np.testing.assert_array_equal(base[name], sent[name], err_msg=name)


def test_gnss_speed_follows_the_ground_speed_within_its_noise_and_latency(runs):
    _, sent = runs
    g = sent["gnss_speed_mps"].astype(float)
    v = np.hypot(sent["vx_true_mps"], sent["vy_true_mps"])
    fix = np.isfinite(g)
    err = g[fix] - v[fix]
    # latency up to 0.2 s at up to 9 m/s^2 of braking: up to 1.8 m/s; most samples within noise + a lag's error
    assert np.median(np.abs(err)) < 0.3
    assert np.all(sent["gnss_speed_accuracy_mps"].astype(float)[fix] >= 0.04)
    assert np.isnan(sent["gnss_speed_accuracy_mps"].astype(float)[~fix]).all()


def test_dropouts_and_outliers_at_their_rates():
    n = 20_000
    t = np.arange(n) * SAMPLE_PERIOD_S
    truth = {"t_s": t, "vx_mps": np.full(n, 20.0), "vy_mps": np.zeros(n)}
    model = ChannelModel(gnss_dropout_share=0.1, gnss_outlier_rate=0.02, gnss_latency_max_s=0.0)
    out = sedan_channels(truth, seed=1, gnss=True, model=model)
    g = out["gnss_speed_mps"]
    assert 0.06 < np.isnan(g).mean() < 0.14
    far = np.abs(g[np.isfinite(g)] - 20.0) > 5 * model.gnss_noise_mps
    assert 0.01 < far.mean() < 0.03
    assert np.isnan(out["drive_force_n"]).all() and np.isnan(out["steering_torque_nm"]).all()


def test_drive_minus_brake_force_is_the_tires_force_within_the_scale_error(runs):
    _, sent = runs
    fx = sum(sent[f"fx_{w}_n"] for w in WHEELS)
    net = sent["drive_force_n"].astype(float) - sent["brake_force_n"].astype(float)
    big = np.abs(fx) > 2000.0
    ratio = net[big] / fx[big]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.12)
    assert (sent["brake_force_n"].astype(float) >= 0.0).all()


def test_brush_trail_shrinks_to_zero_at_full_sliding():
    ca, mu, t0 = 10.0, 0.5, 0.04
    alpha_sl = np.arctan(3.0 * mu / ca)
    alpha = np.array([0.0, 0.5 * alpha_sl, alpha_sl, 2.0 * alpha_sl])
    np.testing.assert_allclose(brush_trail_m(alpha, mu, 4000.0, ca, t0), [t0, 0.5 * t0, 0.0, 0.0], atol=1e-12)


def test_steering_torques_split_the_column_torque_by_the_assist_curve(runs):
    _, sent = runs
    driver = sent["steering_torque_nm"].astype(float)
    assist = sent["eps_assist_torque_nm"].astype(float)
    steering = np.abs(sent["steer_true_rad"]) > 0.01  # the lane change
    assert np.abs(driver[steering]).max() > 0.5
    total = driver + assist
    big = np.abs(total) > 3.0
    # the assist's share of the column torque is the curve's, assist_max |T| / (|T| + assist_half_nm), within noise
    model = ChannelModel()
    share = model.assist_max * np.abs(total[big]) / (np.abs(total[big]) + model.assist_half_nm)
    np.testing.assert_allclose(assist[big] / total[big], share, atol=0.05)


@pytest.mark.parametrize("tire", [DugoffTire(), MagicFormulaTire(), BurckhardtTire(surface="dry_asphalt")])
def test_a_soft_tire_steers_with_the_torque_of_a_stiff_one_at_the_same_force(tire):
    """The pneumatic trail follows the run's own tire: a tire of 0.35 of the stiffness takes 1 / 0.35 of the slip
    angle for the same lateral force, and its full-sliding angle is as much larger, so at the same share of its limit
    the aligning moment, and the column torque, are the same (with the catalogue's stiffness in the trail, the soft
    tire's large angle read as a tire near sliding: 30 % less torque at half the limit)."""
    n, mu, fz = 20, 1.0, 4000.0
    model = ChannelModel(torque_noise_nm=0.0, column_friction_nm=0.0)
    torques = []
    for scale in (1.0, 0.35):
        soft = dataclasses.replace(tire, stiffness_scale=scale)
        c = cornering_stiffness_per_load(soft, MIDSIZE_SEDAN.tire_front, fz, mu)
        fy = 0.5 * mu * fz  # half the limit
        alpha = np.arctan(3.0 * mu / c * (1.0 - (1.0 - fy / (mu * fz)) ** (1.0 / 3.0)))  # the brush model's angle
        truth = {"t_s": np.arange(n) * SAMPLE_PERIOD_S, "steer_rad": np.full(n, 0.05)}
        for w in ("fl", "fr"):
            truth |= {f"mu_{w}": np.full(n, mu), f"fz_{w}_n": np.full(n, fz), f"fy_{w}_n": np.full(n, fy)}
            truth[f"slip_angle_{w}_rad"] = np.full(n, alpha)
        out = sedan_channels(truth, steering=True, model=model, tire=soft)
        torques.append(out["steering_torque_nm"] + out["eps_assist_torque_nm"])
    np.testing.assert_allclose(torques[1], torques[0], rtol=0.02)


def test_the_steering_torques_need_the_tire_model():
    with pytest.raises(ValueError, match="the steering torques need the run's tire model"):
        sedan_channels({"t_s": np.zeros(2)}, steering=True)
