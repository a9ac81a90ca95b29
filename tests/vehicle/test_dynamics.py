"""Body dynamics: the wheel loads of eq. 2 against force and moment balances, the slip ratio of eq. 6, and the state
derivatives at simple equilibria."""

import math

import numpy as np
import pytest

from roadgrip.units import G_MPS2
from roadgrip.vehicle.dynamics import (
    N_STATE,
    PSI,
    SLIP_SPEED_FLOOR_MPS,
    VX,
    VY,
    W0,
    R,
    X,
    Y,
    derivatives,
    pack_vehicle,
    slip_ratio,
    slip_ratio_per_spin,
    wheel_loads,
    wheel_position,
)
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires import DugoffTire

SHIPPED = [PAPER_SUV, MIDSIZE_SEDAN]
SHIPPED_IDS = [v.name for v in SHIPPED]
FL, FR, RL, RR = 0, 1, 2, 3


def loads(vehicle, ax=0.0, ay=0.0, phi=0.0, phid=0.0):
    fz = np.zeros(4)
    wheel_loads(pack_vehicle(vehicle), ax, ay, phi, phid, fz)
    return fz


def positions(vehicle):
    vp = pack_vehicle(vehicle)
    return np.array([wheel_position(vp, i) for i in range(4)])  # (4, 2): x forward, y left of the CoG


def roll_axis_height_m(v):
    """Height of the roll axis under the CoG, interpolated between the front and rear roll centres."""
    return (v.roll_center_height_front_m * v.cg_to_rear_axle_m + v.roll_center_height_rear_m * v.cg_to_front_axle_m) / (
        v.wheelbase_m
    )


# --- wheel positions ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_wheel_positions_follow_iso_8855(vehicle):
    pos = positions(vehicle)
    assert pos[FL] == pytest.approx([vehicle.cg_to_front_axle_m, vehicle.track_front_m / 2])
    assert pos[FR] == pytest.approx([vehicle.cg_to_front_axle_m, -vehicle.track_front_m / 2])
    assert pos[RL] == pytest.approx([-vehicle.cg_to_rear_axle_m, vehicle.track_rear_m / 2])
    assert pos[RR] == pytest.approx([-vehicle.cg_to_rear_axle_m, -vehicle.track_rear_m / 2])


# --- wheel loads (eq. 2) --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_loads_at_rest_carry_the_weight_split_by_the_axle_distances(vehicle):
    fz = loads(vehicle)
    weight_n = vehicle.mass_kg * G_MPS2
    length = vehicle.wheelbase_m
    assert fz.sum() == pytest.approx(weight_n, rel=1e-12)
    assert fz[FL] + fz[FR] == pytest.approx(weight_n * vehicle.cg_to_rear_axle_m / length, rel=1e-12)
    assert fz[RL] + fz[RR] == pytest.approx(weight_n * vehicle.cg_to_front_axle_m / length, rel=1e-12)
    assert fz[FL] == fz[FR] and fz[RL] == fz[RR]
    assert (fz[FL] + fz[FR], fz[RL] + fz[RR]) == pytest.approx(vehicle.static_axle_loads_n, rel=1e-12)


@pytest.mark.parametrize("ax", [-8.0, -2.0, 1.5, 4.0])
@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_longitudinal_acceleration_moves_exactly_m_ax_h_over_l_to_the_rear(vehicle, ax):
    rest = loads(vehicle)
    fz = loads(vehicle, ax=ax)
    transfer_n = vehicle.mass_kg * ax * vehicle.cg_height_m / vehicle.wheelbase_m
    assert fz.sum() == pytest.approx(rest.sum(), rel=1e-12)
    assert (fz[RL] + fz[RR]) - (rest[RL] + rest[RR]) == pytest.approx(transfer_n, rel=1e-9)
    assert (fz[FL] + fz[FR]) - (rest[FL] + rest[FR]) == pytest.approx(-transfer_n, rel=1e-9)
    # pitch balance about the CoG's ground point: sum F_z x = -m a_x h
    x = positions(vehicle)[:, 0]
    assert np.dot(fz, x) == pytest.approx(-vehicle.mass_kg * ax * vehicle.cg_height_m, rel=1e-9)
    assert fz[FL] == fz[FR] and fz[RL] == fz[RR]


@pytest.mark.parametrize(("ay", "phi", "phid"), [(3.0, 0.02, 0.0), (-5.0, -0.04, 0.3), (2.0, -0.01, -0.5)])
@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_lateral_transfer_keeps_the_weight_and_balances_the_roll_moment(vehicle, ay, phi, phid):
    """Per axle: m_axle a_y h_rc / d through the roll centre plus (K phi + C phid) / d through the suspension. Summed
    over the wheels, sum F_z y = -(m a_y h_ra + (K_f + K_r) phi + C phid), h_ra the roll-axis height under the CoG."""
    fz = loads(vehicle, ay=ay, phi=phi, phid=phid)
    assert (fz > 0).all()
    assert fz.sum() == pytest.approx(vehicle.mass_kg * G_MPS2, rel=1e-12)
    rest = loads(vehicle)
    assert fz[FL] + fz[FR] == pytest.approx(rest[FL] + rest[FR], rel=1e-12)  # lateral transfer stays on its axle
    y = positions(vehicle)[:, 1]
    k_total = vehicle.roll_stiffness_front_nmprad + vehicle.roll_stiffness_rear_nmprad
    roll_moment = (
        vehicle.mass_kg * ay * roll_axis_height_m(vehicle) + k_total * phi + vehicle.roll_damping_nmsprad * phid
    )
    assert np.dot(fz, y) == pytest.approx(-roll_moment, rel=1e-9)


@pytest.mark.parametrize("ay", [2.0, 4.0, -3.0])
@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_steady_roll_loads_balance_the_overturning_moment(vehicle, ay):
    """In steady roll, (K_f + K_r) phi = m_s a_y e + m_s g e sin(phi) with e = h - h_ra (the roll equation of
    `derivatives`), and the loads then balance the whole overturning moment about the ground:
    sum F_z y = -(m a_y h_ra + m_s a_y e + m_s g e sin phi). A left turn (a_y > 0) loads the right wheels."""
    h_ra = roll_axis_height_m(vehicle)
    e = vehicle.cg_height_m - h_ra
    ms = vehicle.sprung_mass_kg
    k_total = vehicle.roll_stiffness_front_nmprad + vehicle.roll_stiffness_rear_nmprad
    phi = 0.0
    for _ in range(50):  # fixed point, contraction factor m_s g e / K << 1
        phi = ms * e * (ay + G_MPS2 * math.sin(phi)) / k_total
    fz = loads(vehicle, ay=ay, phi=phi)
    y = positions(vehicle)[:, 1]
    overturning = vehicle.mass_kg * ay * h_ra + ms * ay * e + ms * G_MPS2 * e * math.sin(phi)
    assert np.dot(fz, y) == pytest.approx(-overturning, rel=1e-9)
    assert np.sign(phi) == np.sign(ay)
    outer = (FR, RR) if ay > 0 else (FL, RL)
    inner = (FL, RL) if ay > 0 else (FR, RR)
    assert fz[list(outer)].sum() > fz[list(inner)].sum()


def test_loads_never_go_negative():
    for ay in (-30.0, 30.0):
        for ax in (-15.0, 15.0):
            fz = loads(PAPER_SUV, ax=ax, ay=ay, phi=0.3 * np.sign(ay))
            assert (fz >= 0.0).all()


# --- slip ratio (eq. 6) ---------------------------------------------------------------------------------------------


def test_slip_ratio_is_zero_at_standstill():
    sigma = slip_ratio(0.0, 0.0)
    assert sigma == 0.0
    assert math.isfinite(sigma)


@pytest.mark.parametrize("hub_speed_mps", [0.6, 5.0, 33.0])
def test_locked_wheel_has_slip_minus_one(hub_speed_mps):
    assert slip_ratio(0.0, hub_speed_mps) == -1.0


@pytest.mark.parametrize("speed_mps", [0.0, 0.2, 1.0, 25.0])
def test_free_rolling_wheel_has_zero_slip(speed_mps):
    assert slip_ratio(speed_mps, speed_mps) == 0.0


@pytest.mark.parametrize(
    ("wheel_speed_mps", "hub_speed_mps"),
    [(21.0, 20.0), (19.0, 20.0), (30.0, 20.0), (10.0, 20.0), (3.0, 0.0), (1.0, 2.0)],
)
def test_slip_ratio_is_eq_6(wheel_speed_mps, hub_speed_mps):
    """sigma = (R omega - v) / max(R omega, v): positive when driving, negative when braking."""
    expected = (wheel_speed_mps - hub_speed_mps) / max(wheel_speed_mps, hub_speed_mps)
    assert slip_ratio(wheel_speed_mps, hub_speed_mps) == pytest.approx(expected, rel=1e-15)


def test_slip_ratio_stays_in_minus_one_one_and_finite_near_standstill():
    speeds = np.concatenate([[0.0], np.geomspace(1e-6, 40.0, 60)])
    for w in speeds:
        for v in speeds:
            sigma = slip_ratio(w, v)
            assert math.isfinite(sigma)
            assert -1.0 <= sigma <= 1.0
            if max(w, v) < SLIP_SPEED_FLOOR_MPS:  # below the floor the denominator is the floor
                assert sigma == pytest.approx((w - v) / SLIP_SPEED_FLOOR_MPS)


@pytest.mark.parametrize(
    ("wheel_speed_mps", "hub_speed_mps"),
    [(21.0, 20.0), (19.0, 20.0), (30.0, 20.0), (2.0, 20.0), (0.3, 0.1), (0.1, 0.3)],
)
def test_slip_ratio_per_spin_is_its_derivative(wheel_speed_mps, hub_speed_mps):
    radius = 0.383
    h = 1e-6  # rad/s
    numeric = (
        slip_ratio(wheel_speed_mps + radius * h, hub_speed_mps)
        - slip_ratio(wheel_speed_mps - radius * h, hub_speed_mps)
    ) / (2 * h)
    assert slip_ratio_per_spin(wheel_speed_mps, hub_speed_mps, radius) == pytest.approx(numeric, rel=1e-6)


# --- derivatives ----------------------------------------------------------------------------------------------------


def _derivatives_at(vehicle, x, delta=0.0, drive_torque=None, mu=0.9, ax_prev=0.0, ay_prev=0.0):
    tire = DugoffTire()
    tp = np.stack([tire.row(vehicle.tire_front), tire.row(vehicle.tire_rear)])
    out = {k: np.zeros(4) for k in ("fz", "sigma", "alpha", "fx", "fy", "wheel_k", "wheel_k_secant", "hub_speed")}
    dx = np.zeros(N_STATE)
    torque = np.zeros(4) if drive_torque is None else np.asarray(drive_torque, dtype=float)
    ax, ay = derivatives(
        x,
        delta,
        torque,
        np.full(4, mu),
        pack_vehicle(vehicle),
        tp,
        ax_prev,
        ay_prev,
        dx,
        out["fz"],
        out["sigma"],
        out["alpha"],
        out["fx"],
        out["fy"],
        out["wheel_k"],
        out["wheel_k_secant"],
        out["hub_speed"],
    )
    return dx, ax, ay, out


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_vehicle_at_rest_stays_at_rest(vehicle):
    dx, ax, ay, out = _derivatives_at(vehicle, np.zeros(N_STATE))
    assert np.all(dx == 0.0)
    assert ax == 0.0 and ay == 0.0
    assert np.all(out["sigma"] == 0.0) and np.all(out["alpha"] == 0.0)
    assert out["fz"].sum() == pytest.approx(vehicle.mass_kg * G_MPS2, rel=1e-12)


@pytest.mark.parametrize("heading_rad", [0.0, 0.7, -2.5])
def test_free_rolling_straight_only_feels_the_air(heading_rad):
    """Wheels at v / R, no steer: no tire force; the only acceleration is the drag 0.5 rho C_d A v^2 / m."""
    v, speed = PAPER_SUV, 25.0
    x = np.zeros(N_STATE)
    x[PSI], x[VX] = heading_rad, speed
    x[W0 : W0 + 4] = speed / v.wheel_radius_m
    dx, ax, ay, out = _derivatives_at(v, x)
    assert np.all(out["fx"] == 0.0) and np.all(out["fy"] == 0.0)
    drag = 0.5 * 1.225 * v.drag_coefficient * v.frontal_area_m2 * speed**2
    assert ax == pytest.approx(-drag / v.mass_kg, rel=1e-12)
    assert ay == 0.0 and dx[R] == 0.0 and dx[VY] == 0.0
    assert np.all(dx[W0 : W0 + 4] == 0.0)
    assert (dx[X], dx[Y]) == pytest.approx((speed * math.cos(heading_rad), speed * math.sin(heading_rad)), rel=1e-12)


def test_positive_steer_turns_left():
    v = PAPER_SUV
    x = np.zeros(N_STATE)
    x[VX] = 20.0
    x[W0 : W0 + 4] = 20.0 / v.wheel_radius_m
    dx, _ax, ay, out = _derivatives_at(v, x, delta=0.02)
    assert out["alpha"][0] == pytest.approx(0.02) and out["alpha"][2] == 0.0  # eq. 8 at the front, zero at the rear
    assert out["fy"][0] > 0 and out["fy"][1] > 0
    assert ay > 0.0 and dx[R] > 0.0  # pushed to the left, yawing to the left
    # left and right see the same forces, so only the front axle's lateral force turns the car:
    # I_z r' = l_f sum (F_x sin(delta) + F_y cos(delta)) (eq. 1, wheel frame to body frame)
    lateral_n = (out["fx"][:2] * math.sin(0.02) + out["fy"][:2] * math.cos(0.02)).sum()
    assert dx[R] == pytest.approx(v.cg_to_front_axle_m * lateral_n / v.yaw_inertia_kgm2, rel=1e-9)
    assert ay == pytest.approx((lateral_n + out["fy"][2:].sum()) / v.mass_kg, rel=1e-9)
