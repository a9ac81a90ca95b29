"""The single-track (bicycle) model pieces of pmf's lateral channel: the steer's reference, the axles' forces per load,
the brush model's slip angle, and the likelihood over mu of a measured understeer angle.

Single-track model (Rajamani, Vehicle Dynamics and Control, 2nd ed., section 3.3, small angles): each axle's lateral
force is its cornering stiffness times its slip angle, C_f alpha_f and C_r alpha_r (N/rad, both tires), and in a steady
turn the road-wheel angle is

    delta = L / R + K_us a_y,     K_us = (m / L) (l_r / C_f - l_f / C_r)      (Rajamani eq. 3.14-3.15)

With the stiffness per load the profile gives (C_f = c_f F_z,f, F_z,f = m g l_r / L, likewise at the rear), the masses
cancel: K_us = (1 / c_f - 1 / c_r) / g. The yaw rate the steer asks for in a steady turn (a_y = v r, R = v / r) is

    r_ref = v delta / (L + K_us v^2)                                          (Rajamani eq. 3.16)

which for a neutral-steer car (K_us = 0) is the kinematic v delta / L.

Without the steady state: the axles' slip angles are alpha_f = delta - (v_y + l_f r) / v and alpha_r = -(v_y - l_r r) / v
(Rajamani eq. 2.30-2.31), so their difference, the understeer angle

    delta - L r / v = alpha_f - alpha_r                                        (exact: the unmeasured v_y cancels)

is measured at every sample, in a transient as in a steady turn. The axles' forces follow from Newton-Euler for the
body (Rajamani eq. 2.27-2.28, the front force taken across the body, cos delta ~ 1):
F_y,f = (m l_r a_y + I_z r') / L, F_y,r = (m l_f a_y - I_z r') / L; per load, f = F_y / F_z.

The brush model (Pacejka, Tyre and Vehicle Dynamics, 3rd ed., section 3.2.2) gives each axle's slip angle at force per
load f on a road of friction mu and a tire of cornering stiffness per load c:

    tan alpha = (3 mu / c) (1 - (1 - |f| / mu)^(1/3)) sign(f)       (|f| < mu; alpha = f / c at small f, whatever mu)

so an axle's slip angle grows faster than f / c as it nears its limit: the understeer angle bends away from its line
K_us a_y where the front axle nears its limit (understeer), and towards zero or below where the rear does (oversteer).
That bend, on the calibrated line, is the evidence over mu. An axle also driven or braked has less left for the side
(the friction ellipse, Pacejka section 3.2.4): mu_y = sqrt(mu^2 - f_x^2).

The kinematic angle L r / v is the profile's: its wheelbase, the steering ratio that turns the steering wheel's angle
into delta, and the speed from the wheels' rolling radius are each known to a few percent, and each error scales the
whole angle. In a 20 m turn at 4.5 m/s that angle is 0.13 rad against slip angles of 0.007: 4 % of it is an ice
tire's bend. So the understeer angle is read as k_f alpha_f - k_r alpha_r + e L r / v, with the scale error e
marginalised alongside the tires' compliances.
"""

from __future__ import annotations

from math import erf, exp, sqrt

import numpy as np
from numba import njit
from scipy.special import ndtr

from roadgrip.units import G_MPS2

# The combined-slip floor: an axle whose longitudinal force per load reaches mu still holds some of it sideways (the
# ellipse's ends are where the brush model's force direction follows the slip's; 0.1 keeps the lateral curve defined)
LATERAL_SHARE_FLOOR = 0.1
# The brush model's bend against other tire curves: at 60 % of the limit the brush's slip angle is 1.32 x the line,
# a Magic Formula's (C = 1.4) 1.16 x and Dugoff's 1.04 x (linear to half the limit); at 85 % 1.64, 1.45 and 1.67. Their
# excess over the line differs from the brush's by half of it and more: the error allowed is half the excess
LATERAL_MODEL_SHARE = 0.5


@njit(cache=True)
def understeer_gradient(c_front_per_rad, c_rear_per_rad):
    """K_us (rad per m/s^2) from each axle's cornering stiffness per load (per rad): (1 / c_f - 1 / c_r) / g."""
    return (1.0 / c_front_per_rad - 1.0 / c_rear_per_rad) / G_MPS2


@njit(cache=True)
def reference_yaw_rate(v_mps, delta_rad, wheelbase_m, k_us):
    """The steady-state yaw rate the road-wheel angle asks for, v delta / (L + K_us v^2) (Rajamani eq. 3.16)."""
    return v_mps * delta_rad / (wheelbase_m + k_us * v_mps * v_mps)


@njit(cache=True)
def axle_lateral_per_load(m, lf, lr, iz, ay, yaw_accel, fz_front, fz_rear):
    """(f_front, f_rear): each axle's lateral force per its load, from the body's a_y and yaw acceleration."""
    wb = lf + lr
    fy_front = (m * lr * ay + iz * yaw_accel) / wb
    fy_rear = (m * lf * ay - iz * yaw_accel) / wb
    return fy_front / fz_front, fy_rear / fz_rear


@njit(cache=True)
def lateral_friction(mu, fx):
    """What the friction ellipse leaves for the side of an axle carrying fx per load on a road of friction mu (Pacejka
    section 3.2.4): sqrt(mu^2 - fx^2), at least LATERAL_SHARE_FLOOR of mu."""
    return sqrt(max(mu * mu - fx * fx, (LATERAL_SHARE_FLOOR * mu) ** 2))


@njit(cache=True)
def brush_slip(f, mu, c):
    """The brush model's slip at force per load f (signed), friction mu, slip stiffness per load c:
    (3 mu / c) (1 - (1 - |f| / mu)^(1/3)), signed as f, its value at |f| = mu beyond (Pacejka 3.2). With an isotropic
    brush the form is the same for the longitudinal slip ratio and the tan of the slip angle: pmf's axle-slip term
    and the lateral channel both read it here."""
    x = min(abs(f) / mu, 1.0)
    a = 3.0 * mu / c * (1.0 - (1.0 - x) ** (1.0 / 3.0))
    return -a if f < 0.0 else a


@njit(cache=True)
def brush_slip_angle(f, mu, c):
    """The brush model's (tan of the) slip angle at force per load f (signed), friction mu, stiffness per load c, and
    whether the axle is at its limit (|f| >= mu: the slip angle is then at least the returned one)."""
    return brush_slip(f, mu, c), abs(f) / mu >= 1.0


@njit(cache=True)
def brush_slip_angle_slope(f, mu, c):
    """d alpha / d f of the brush model: (1 / c) (1 - |f| / mu)^(-2/3), capped where the axle nears its limit."""
    return (1.0 / c) * max(1.0 - abs(f) / mu, 0.01) ** (-2.0 / 3.0)


# Phi tabulated on [-CDF_TABLE_END, CDF_TABLE_END] every 1 / CDF_TABLE_PER_UNIT (scipy's ndtr) and read between its
# points linearly: the error is at most h^2 / 8 |Phi''| = h^2 / 8 |x| phi(x), 2.9e-8 at |x| = 1 and under 5e-6 of Phi
# itself in the low tail. 3 ns a call against erf's 20 (results/trials/estimators/normal_cdf_speed.py): ABS's
# likelihood reads it 1,000-2,150 times a sample
CDF_TABLE_END = 6.0
CDF_TABLE_PER_UNIT = 1024
CDF_TABLE = ndtr(
    np.arange(-CDF_TABLE_END * CDF_TABLE_PER_UNIT, CDF_TABLE_END * CDF_TABLE_PER_UNIT + 2) / CDF_TABLE_PER_UNIT
)


@njit(cache=True)
def normal_cdf(x):
    """Phi(x), the standard normal distribution function (compiled; pmf's likelihoods use it too): CDF_TABLE read
    linearly within its span, erf beyond it."""
    if not -CDF_TABLE_END < x < CDF_TABLE_END:
        return 0.5 * (1.0 + erf(x / sqrt(2.0)))
    u = (x + CDF_TABLE_END) * CDF_TABLE_PER_UNIT
    k = int(u)
    return CDF_TABLE[k] + (u - k) * (CDF_TABLE[k + 1] - CDF_TABLE[k])


# The lateral state (lateral_likelihood's `comp`, and `post` a grid mu): the means of the front and rear tires'
# cornering compliance over the profile's and of the kinematic angle's scale error, then their covariance's upper
# triangle (00, 01, 02, 11, 12, 22)
N_LATERAL_PARAMS = 3
N_COMPLIANCE = N_LATERAL_PARAMS + N_LATERAL_PARAMS * (N_LATERAL_PARAMS + 1) // 2


# the covariance's upper triangle, entry by entry (row, column), in the state's order
TRI_ROW, TRI_COL = np.triu_indices(N_LATERAL_PARAMS)


@njit(cache=True)
def unpack_gaussian(comp, mean, cov):
    """The lateral state's means and covariance (comp: N_COMPLIANCE numbers) into a vector and a symmetric matrix."""
    mean[:] = comp[:N_LATERAL_PARAMS]
    for k in range(TRI_ROW.size):
        cov[TRI_ROW[k], TRI_COL[k]] = cov[TRI_COL[k], TRI_ROW[k]] = comp[N_LATERAL_PARAMS + k]


@njit(cache=True)
def pack_gaussian(mean, cov, out):
    """unpack_gaussian's inverse: a vector and a symmetric matrix into N_COMPLIANCE numbers."""
    out[:N_LATERAL_PARAMS] = mean
    for k in range(TRI_ROW.size):
        out[N_LATERAL_PARAMS + k] = cov[TRI_ROW[k], TRI_COL[k]]


@njit(cache=True)
def lateral_likelihood(
    mu_grid,
    comp,
    understeer,
    kinematic,
    f_front,
    f_rear,
    fx_front,
    fx_rear,
    c_front,
    c_rear,
    var0,
    sf,
    temper,
    out,
    post,
):
    """The likelihood over mu (out, one value per grid mu) of a measured understeer angle (rad, the calibrated offset
    taken out), raised to `temper`, with the tires' compliances and the kinematic angle's scale marginalised; f_*: the
    axles' lateral, fx_*: their longitudinal forces per load; kinematic: the angle L r / v the understeer angle
    subtracts.

    Given mu the understeer angle is linear in the front and rear tires' compliances over the profile's (k_f, k_r) and
    in the kinematic angle's scale error e: k_f a_f - k_r a_r + e L r / v, a_* the brush model's slip angles at the
    profile's stiffnesses. e is what the profile's wheelbase and steering ratio and the wheels' rolling radius (the
    speed v) get wrong: each moves the kinematic angle in proportion, which at walking pace in a tight turn is 20 times
    the tires' slip angles. comp holds the three's Gaussian (N_COMPLIANCE numbers), so each mu's likelihood is the
    Kalman filter's predictive density of the tempered measurement, N(y; h m, s) with h = (a_f, -a_r, L r / v) and
    s = h P h' + R / temper, times sqrt(2 pi R / temper): 1 at y = h m with the three known (P = 0), the one-sided
    terms' scale. post gets each mu's Kalman update (m + K e, P - K h P: N_COMPLIANCE numbers a mu). var0: the variance
    of the measurement and of the calibrated offset; R adds the brush model's error against other tires
    (LATERAL_MODEL_SHARE of its bend) and the force per load's standard deviation sf (the lateral accelerometer's
    remaining bias over g) through the brush model's slope, each at the mean compliances. An axle at its limit
    (|f| >= mu_y) only bounds its slip angle from below: the likelihood is then one-sided (and post is comp), and
    uninformative where both axles are: there the likelihood is the nearest cell's with an axle that holds (from
    above), so that a sample the model fits badly does not favour the cells where it says nothing (the friction bound
    judges those)."""
    n, d = N_COMPLIANCE, N_LATERAL_PARAMS
    mean = np.empty(d)
    cov = np.empty((d, d))
    unpack_gaussian(comp, mean, cov)
    h = np.empty(d)
    ph = np.empty(d)
    for i in range(mu_grid.size - 1, -1, -1):
        mu = mu_grid[i]
        for k in range(n):
            post[i * n + k] = comp[k]
        mu_f = lateral_friction(mu, fx_front)
        mu_r = lateral_friction(mu, fx_rear)
        a_f, sat_f = brush_slip_angle(f_front, mu_f, c_front)
        a_r, sat_r = brush_slip_angle(f_rear, mu_r, c_rear)
        h[0], h[1], h[2] = a_f, -a_r, kinematic
        excess = mean[0] * (a_f - f_front / c_front) - mean[1] * (a_r - f_rear / c_rear)
        d_slope = mean[0] * brush_slip_angle_slope(f_front, mu_f, c_front) - mean[1] * brush_slip_angle_slope(
            f_rear, mu_r, c_rear
        )
        r = var0 + (LATERAL_MODEL_SHARE * excess) ** 2 + (sf * d_slope) ** 2
        pred = 0.0
        hph = 0.0
        for a in range(d):
            pred += h[a] * mean[a]
            ph[a] = 0.0
            for b in range(d):
                ph[a] += cov[a, b] * h[b]
        for a in range(d):
            hph += h[a] * ph[a]
        if sat_f and sat_r:
            out[i] = out[i + 1] if i + 1 < mu_grid.size else 1.0
        elif sat_f:  # the front slides: the understeer angle is at least (in the force's direction) the prediction
            sig = sqrt(r + hph)
            out[i] = normal_cdf((understeer - pred) / sig if f_front > 0.0 else (pred - understeer) / sig) ** temper
        elif sat_r:  # the rear slides: the understeer angle is at most the prediction
            sig = sqrt(r + hph)
            out[i] = normal_cdf((pred - understeer) / sig if f_rear > 0.0 else (understeer - pred) / sig) ** temper
        else:
            s = hph + r / temper  # the innovation's variance, the tempered measurement's R / temper
            e = understeer - pred
            out[i] = sqrt(r / (temper * s)) * exp(-0.5 * e * e / s)
            # K = P h' / s; m = m + K e; P = P - K h P
            for a in range(d):
                post[i * n + a] = mean[a] + ph[a] / s * e
            for k in range(TRI_ROW.size):
                a, b = TRI_ROW[k], TRI_COL[k]
                post[i * n + d + k] = cov[a, b] - ph[a] * ph[b] / s
