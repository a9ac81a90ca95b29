"""The filters' shared model against closed forms, finite differences and the simulator (a second implementation)."""

import numpy as np
import pytest

from roadgrip.estimators.vehicle_model import (
    MU,
    N_U,
    N_X,
    N_Z,
    SCALE,
    VX,
    VY,
    Z_AX,
    Z_AY,
    Z_R,
    Z_V,
    FilterTuning,
    R,
    dugoff_partials,
    loads_from_accel,
    measure,
    pack_model,
    predict_state,
    roll_per_lateral_accel,
)
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import PAPER_SUV
from roadgrip.vehicle.tires.dugoff import DugoffTire, dugoff_forces

PRM = pack_model(PAPER_SUV)
TP = DugoffTire().row(PAPER_SUV.tire_front)
FZ_N = 5500.0


def _partials(sigma, alpha, mu, fz=FZ_N):
    out = np.empty(8)
    dugoff_partials(TP, sigma, alpha, fz, mu, out)
    return out


def _lambda(sigma, alpha, mu, fz=FZ_N):
    cx, cy = TP[1] * fz, TP[2] * fz
    return mu * fz * (1 + sigma) / (2 * np.hypot(cx * sigma, cy * np.tan(alpha)))


@pytest.mark.parametrize(
    "sigma, alpha, mu",
    [
        (0.002, 0.001, 0.9),
        (-0.004, 0.01, 0.8),
        (0.05, 0.02, 0.3),
        (-0.15, 0.0, 0.6),
        (-0.1, -0.05, 0.2),
        (0.0, 0.08, 0.4),
        (-1.0, 0.1, 0.5),
        (0.3, -0.3, 1.2),
        (0.0, 0.0, 0.5),
    ],
)
def test_dugoff_partials_give_the_simulators_forces(sigma, alpha, mu):
    out = _partials(sigma, alpha, mu)
    assert (out[0], out[1]) == dugoff_forces(TP, sigma, alpha, FZ_N, mu)


@pytest.mark.parametrize(
    "sigma, alpha, mu",
    [
        (0.002, 0.001, 0.9),
        (-0.004, 0.01, 0.8),
        (0.05, 0.02, 0.3),
        (-0.15, 0.0, 0.6),
        (-0.1, -0.05, 0.2),
        (0.0, 0.08, 0.4),
        (0.3, -0.3, 1.2),
    ],
)
def test_dugoff_partials_match_central_differences(sigma, alpha, mu):
    assert abs(_lambda(sigma, alpha, mu) - 1.0) > 0.05, "a case must stay clear of the kink at lambda = 1"
    out = _partials(sigma, alpha, mu)
    for k, (ds, da, dm) in enumerate([(1e-7, 0, 0), (0, 1e-7, 0), (0, 0, 1e-7)]):
        hi = _partials(sigma + ds, alpha + da, mu + dm)
        lo = _partials(sigma - ds, alpha - da, mu - dm)
        step = 2e-7
        assert out[2 + k] == pytest.approx((hi[0] - lo[0]) / step, rel=1e-5, abs=1e-3)
        assert out[5 + k] == pytest.approx((hi[1] - lo[1]) / step, rel=1e-5, abs=1e-3)


def test_dugoff_limits_zero_slip_zero_force_and_mu_only_where_saturated():
    assert tuple(_partials(0.0, 0.0, 0.7)[:2]) == (0.0, 0.0)
    linear = _partials(0.004, 0.0, 0.9)  # lambda = 4.5: linear, force C_x sigma / (1 + sigma), no mu in it
    assert linear[0] == pytest.approx(TP[1] * FZ_N * 0.004 / 1.004) and linear[4] == 0.0
    for sigma in (-0.2, -0.5, -0.99):
        sat = _partials(sigma, 0.0, 0.4)
        assert abs(sat[0]) <= 0.4 * FZ_N and sat[4] < 0.0  # |F| <= mu F_z; braking force grows with mu
    assert abs(_partials(-0.99, 0.0, 0.4)[0]) == pytest.approx(0.4 * FZ_N, rel=0.01)  # locked: F -> mu F_z


def _states():
    """(x, u) cases: cruise, braking with saturated tires, cornering with steer, low speed."""
    cases = []
    for vx, vy, r, mu, spins, delta, ax, ay in [
        (25.0, 0.0, 0.0, 0.8, [65.4, 65.4, 65.3, 65.3], 0.0, 0.3, 0.0),
        (20.0, 0.05, 0.01, 0.3, [45.0, 46.0, 48.0, 47.5], 0.0, -2.8, 0.1),
        (15.0, 0.3, 0.25, 0.6, [39.6, 39.0, 39.3, 38.8], 0.06, 0.1, 3.5),
        (14.0, -0.5, -0.35, 0.35, [36.0, 37.5, 36.6, 37.2], -0.08, -0.5, -3.0),
        (3.0, 0.0, 0.0, 0.5, [7.9, 7.9, 7.8, 7.8], 0.0, 0.5, 0.0),
    ]:
        x = np.array([vx, vy, r, 0.004, mu])
        u = np.array([*spins, delta, ax, ay])
        cases.append((x, u))
    return cases


@pytest.mark.parametrize("x, u", _states())
def test_measurement_jacobians_match_finite_differences(x, u):
    fz = np.empty(4)
    loads_from_accel(PRM, u[5], u[6], fz)
    z, H, G = np.empty(N_Z), np.empty((N_Z, N_X)), np.empty((N_Z, 4))
    measure(x, u, PRM, fz, z, H, G)
    zz, HH, GG = np.empty(N_Z), np.empty((N_Z, N_X)), np.empty((N_Z, 4))

    def h(x_, u_):
        measure(x_, u_, PRM, fz, zz, HH, GG)
        return zz.copy()

    for j, step in zip(range(N_X), (1e-6, 1e-6, 1e-7, 1e-7, 1e-7)):
        e = np.zeros(N_X)
        e[j] = step
        fd = (h(x + e, u) - h(x - e, u)) / (2 * step)
        np.testing.assert_allclose(H[:, j], fd, rtol=1e-4, atol=1e-4, err_msg=f"dh/dx[{j}]")
    for i in range(4):
        e = np.zeros(N_U)
        e[i] = 1e-6
        fd = (h(x, u + e) - h(x, u - e)) / 2e-6
        np.testing.assert_allclose(G[:, i], fd, rtol=1e-4, atol=1e-4, err_msg=f"dh/domega[{i}]")


@pytest.mark.parametrize("x, u", _states())
def test_process_jacobian_matches_finite_differences(x, u):
    u_prev = u + np.array([0, 0, 0, 0, 0, 0.4, -0.3])
    x_out, F = np.empty(N_X), np.empty((N_X, N_X))
    predict_state(x, u_prev, u, 0.1, PRM, x_out, F)
    xo, FF = np.empty(N_X), np.empty((N_X, N_X))
    for j in range(N_X):
        e = np.zeros(N_X)
        e[j] = 1e-6
        predict_state(x + e, u_prev, u, 0.1, PRM, xo, FF)
        hi = xo.copy()
        predict_state(x - e, u_prev, u, 0.1, PRM, xo, FF)
        np.testing.assert_allclose(F[:, j], (hi - xo) / 2e-6, rtol=1e-6, atol=1e-9)


def test_process_integrates_a_constant_acceleration_exactly():
    x = np.array([10.0, 0.0, 0.0, 0.0, 0.5])
    u = np.array([26.0, 26.0, 26.0, 26.0, 0.0, -3.0, 0.0])
    x_out, F = np.empty(N_X), np.empty((N_X, N_X))
    for _ in range(20):  # 2 s at -3 m/s^2 on a straight: vx = 10 - 3 t, nothing else moves
        predict_state(x, u, u, 0.1, PRM, x_out, F)
        x = x_out.copy()
    assert x[VX] == pytest.approx(4.0, abs=1e-12) and x[VY] == 0.0 and x[R] == 0.0 and x[MU] == 0.5


def test_loads_carry_the_weight_and_the_roll_gain_is_the_steady_state_one():
    fz = np.empty(4)
    for ax, ay in [(0.0, 0.0), (-6.0, 0.0), (2.0, 4.0), (-3.0, -5.0)]:
        loads_from_accel(PRM, ax, ay, fz)
        assert fz.sum() == pytest.approx(PAPER_SUV.mass_kg * G_MPS2)
    loads_from_accel(PRM, -6.0, 0.0, fz)
    assert fz[0] > fz[2] and fz[0] == pytest.approx(fz[1])  # braking loads the front axle
    # steady state of the simulator's roll equation: (K_f + K_r) phi = m_s e (a_y + g phi), e the roll arm
    v = PAPER_SUV
    e = v.cg_height_m - (
        v.roll_center_height_front_m
        + (v.roll_center_height_rear_m - v.roll_center_height_front_m) * v.cg_to_front_axle_m / v.wheelbase_m
    )
    k_phi = roll_per_lateral_accel(v)
    phi = k_phi * 3.0
    assert (v.roll_stiffness_front_nmprad + v.roll_stiffness_rear_nmprad) * phi == pytest.approx(
        v.sprung_mass_kg * e * (3.0 + G_MPS2 * phi)
    )


def test_measurement_model_reproduces_the_simulator_on_its_true_state():
    """h at the simulator's true state, with its noiseless telemetry as inputs, is the noiseless telemetry: in a
    steady curve (roll, lateral load transfer, slip angles) and in ABS braking (saturated tires)."""
    curve = Scenario(
        run_id="curve",
        path=Path.circle(80.0, 800.0),
        mu=MuProfile.uniform(0.8),
        speed=SpeedProfile([0.0, 30.0], [8.0, 17.0]),
        duration_s=30.0,
    )
    brake = Scenario(
        run_id="brake",
        path=Path.straight(600.0),
        mu=MuProfile.uniform(0.6),
        speed=SpeedProfile([0.0, 2.0, 2.3, 10.0], [25.0, 25.0, 0.0, 0.0]),
        duration_s=10.0,
    )
    table = simulate([curve, brake], SensorModel.noiseless())
    fz, z, H, G = np.empty(4), np.empty(N_Z), np.empty((N_Z, N_X)), np.empty((N_Z, 4))
    err = {"ax": [], "ay": []}
    for row in table.to_pylist():
        if row["t_s"] < 3.0 or row["vx_true_mps"] < 5.0:
            continue
        x = np.array([row["vx_true_mps"], row["vy_true_mps"], row["yaw_rate_true_radps"], 0.0, row["mu"]])
        u = np.array(
            [row[f"wheel_speed_{w}_radps"] for w in ("fl", "fr", "rl", "rr")]
            + [row["steering_wheel_angle_rad"] / PAPER_SUV.steering_ratio, row["accel_lon_mps2"], row["accel_lat_mps2"]]
        )
        loads_from_accel(PRM, u[5], u[6], fz)
        measure(x, u, PRM, fz, z, H, G)
        err["ax"].append(z[Z_AX] - row["accel_lon_mps2"])
        err["ay"].append(z[Z_AY] - row["accel_lat_mps2"])
        assert z[Z_R] == row["yaw_rate_true_radps"] and z[Z_V] == row["vx_true_mps"]
    # what is left: the loads use this sample's accelerations and the steady-state roll, where the simulator uses the
    # previous integration step's accelerations and its roll state (0.002 and 0.0004 m/s^2 RMS when written)
    assert np.sqrt(np.mean(np.square(err["ax"]))) < 0.01
    assert np.sqrt(np.mean(np.square(err["ay"]))) < 0.005
    assert len(err["ay"]) > 250


def test_speed_measurement_carries_the_scale_error():
    x = np.array([20.0, 0.0, 0.0, 0.01, 0.5])
    u = np.array([52.2] * 4 + [0.0, 0.0, 0.0])
    fz, z, H, G = np.empty(4), np.empty(N_Z), np.empty((N_Z, N_X)), np.empty((N_Z, 4))
    loads_from_accel(PRM, 0.0, 0.0, fz)
    measure(x, u, PRM, fz, z, H, G)
    assert z[Z_V] == pytest.approx(20.2) and H[Z_V, SCALE] == 20.0 and H[Z_V, VX] == pytest.approx(1.01)


def test_bad_arguments_are_refused_with_the_field_named():
    with pytest.raises(TypeError, match="VehicleParams"):
        pack_model({"mass_kg": 1500})
    with pytest.raises(ValueError, match="excitation_snr"):
        FilterTuning(excitation_snr=-1.0)
    with pytest.raises(ValueError, match="unknown FilterTuning key"):
        FilterTuning.from_dict({"mu_prior": 0.5})
    assert FilterTuning.from_dict(FilterTuning().to_dict()) == FilterTuning()
