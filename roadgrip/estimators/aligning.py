"""pmf's steering-torque term (CONTRACTS 3.1: steering_torque_nm, eps_assist_torque_nm): the front axle's aligning
moment, whose pneumatic trail shrinks long before the lateral force saturates (Hsu, Laws and Gerdes, "Estimation of
tire slip angle and friction limits using steering torque", IEEE TCST 18(4), 2010). Compiled helpers that pmf's step
calls; the grid and the likelihood's application stay pmf's.

The moment. The driver's and the EPS motor's torques add to the column torque T; through the steering ratio n it is
the front axle's aligning moment plus the column's Coulomb friction, which acts against the steering rate:

    n (T - T_c tanh(n delta' / w_c)) = M = (t_p + t_m) F_y,f

t_m the caster's mechanical trail (the profile's `mechanical_trail_m`), t_p the pneumatic trail, F_y,f the front axle's
lateral force (lateral.py `axle_lateral_per_load`, from a_y and the yaw acceleration: Newton-Euler).

The brush model (Pacejka, Tyre and Vehicle Dynamics, 3rd ed., 3.2): with theta = tan(alpha) / tan(alpha_sl) and
alpha_sl the full-sliding angle, the force per load is f = mu (1 - (1 - theta)^3) and the trail, linearised,
t_p = t0 (1 - theta), so at the force per load f

    t_p = t0 (1 - |f| / mu)^(1/3)             (0.79 t0 at half the limit, 0.59 t0 at 0.8 of it)

while the force's own bend against its line is within the tires' stiffness spread up to about 0.9 of the limit
(docs/RESULTS.md, "The lateral channel with a correlated stiffness spread"). An axle also braked or driven has
mu_y = sqrt(mu^2 - f_x^2) left for the side (the friction ellipse, as lateral.py).

Calibration. The profile's t0 (the front tire's `pneumatic_trail_m`) is nominal, real tires differ, and a car's torque
scale may be nominal too (the RAV4's 0.01 N m a count, docs/PRODUCTION.md): the term reads the moment relative to the
car's own driving. A gain g on the profile's trail, M = g (t0 (1 - |f| / mu)^(1/3) + t_m) F_y,f, is learned by
recursive least squares with forgetting (RLS_TAU_S, as pmf's other lines), one gain for each mu of pmf's grid: in calm
driving (|f| well under every plausible mu) the trail is t0 under every hypothesis and all of them learn the same gain,
the car's calibration; nearer the limit each hypothesis reads the trail under its own mu, so a car on ice does not
learn its shrunken trail as its tire's, and no calm phase is needed (a single gain learned only where the posterior
called the driving calm, the first design, saw 0.4 s of calm cornering on a 30 s ice ramp steer and never spoke).
The likelihood of a sample under a mu is the prediction of that mu's line before the sample (mean g h, variance
h^2 P_g + the sample's own), so the product over samples is each hypothesis's marginal likelihood with its gain
integrated out: a gain that must keep moving to follow the data (the trail shrinking under a hypothesis that says it
should not) pays at every sample. A hypothesis learns
only below CALIBRATION_MAX_X of its limit (where its trail is not near zero) and at |f| >= CALIBRATION_MIN_F (below
it the regressor is mostly its own noise, which would pull the gain towards zero).

The evidence. After CALIBRATED_S of readable driving, at |f| >= EVIDENCE_MIN_F, off at a controller's limit (ABS,
traction control, ESC), a wheel past its peak or below pmf's ALIGNING_MIN_SPEED_MPS: the spread is the torque noise,
the column friction's remaining error, the gain's variance (and its floor GAIN_FLOOR: the trail varies with load and
temperature), the force per load's error (the lateral accelerometer's noise and remaining bias, and the force's change
between samples times the signals' time offset, each times the trail) and the brush model's error against real tires
(MODEL_SHARE of the trail's reduction t0 - t_p). A mu under which the front axle would be past its limit (|f| >= mu_y)
is not judged here (the friction bound does that): it takes the value of the nearest mu above it.

Not modelled: the trail's dependence on load transfer between the left and right wheels (each wheel's own trail at its
own slip angle; the axle's sum is read as one trail), the EPS's own friction compensation and damping (they shift the
column friction's size: COLUMN_FRICTION_SD_NM), jacking and steering-axis moments at large steer angles (no gate:
they centre the wheels, so a tight turn's column torque reads as a longer trail, grippier, not as ice), and a torque
sign that differs from ISO 8855's (positive left) in a car's mapping.
"""

from __future__ import annotations

from math import exp, tanh

import numpy as np
from numba import njit

from roadgrip.estimators.lateral import lateral_friction

# The column
TORQUE_NOISE_NM = 0.05  # each torque signal's noise (a column torque sensor: 0.02-0.1 N m)
COLUMN_FRICTION_NM = 0.4  # the column's Coulomb friction seen by the torque sensors (EPS columns: 0.1-1 N m)
COLUMN_FRICTION_SD_NM = 0.3  # ... its spread between cars and with the EPS's friction compensation
FRICTION_RATE_RADPS = 0.05  # the handwheel's rate (rad/s) above which the friction is fully against it
# The calibration
RLS_TAU_S = 120.0  # the gain's memory (as pmf's lines)
GAIN_SD0 = 0.3  # an uncalibrated car: the tire's trail and the torque scale +-30 % against the profile's
GAIN_RANGE = (0.2, 5.0)  # a torque scale far off the nominal (an unknown count size) still calibrates
CALIBRATION_MIN_F = 0.03  # a readable trail: a moment of 20-30 N m at the wheels against about 5 of friction
CALIBRATION_MAX_X = 0.9  # a hypothesis learns its gain where its front axle is under 0.9 of its limit (t_p > 0.46 t0)
CALIBRATED_S = 1.0  # the term speaks after this much readable driving (10 samples: the gains off their prior)
# The evidence
GAIN_FLOOR = 0.05  # what calibration leaves: the trail with the load, the tire's temperature, the road's texture
EVIDENCE_MIN_F = 0.05  # below this the trail's reduction is within the column friction's error
MODEL_SHARE = 0.5  # the brush model's linear trail against measured trails (Pacejka 3.2 Fig. 3.7): half its reduction
TIME_OFFSET_S = 0.05  # the torque and IMU signals read up to 50 ms apart (pmf's LAT_TIME_OFFSET_S)
# Memory block (offsets from its start): bookkeeping, then each grid mu's gain and its variance
A_F_PREV, A_W, A_USED = range(3)
A_CELLS = 3


def memory_size(n_mu: int) -> int:
    """The block's length for a grid of n_mu values."""
    return A_CELLS + 2 * n_mu


@njit(cache=True)
def init_aligning_memory(mem, base, n_mu):
    """The block's start: every hypothesis at the profile's trail (gain 1) with the prior's variance, no data."""
    for k in range(A_CELLS):
        mem[base + k] = 0.0
    for i in range(n_mu):
        mem[base + A_CELLS + 2 * i] = 1.0
        mem[base + A_CELLS + 2 * i + 1] = GAIN_SD0**2


@njit(cache=True)
def trail_factor(f, mu):
    """t_p / t0 of the brush model at force per load f and friction mu: (1 - |f| / mu)^(1/3), 0 at the limit."""
    x = min(abs(f) / mu, 1.0)
    return (1.0 - x) ** (1.0 / 3.0)


@njit(cache=True)
def torques_sent(driver_nm, eps_nm):
    """Whether the car sends both torques (NaN: not sent)."""
    return np.isfinite(driver_nm) and np.isfinite(eps_nm)


@njit(cache=True)
def aligning_step(
    mem,
    base,
    driver_nm,
    eps_nm,
    dt,
    steer_rate_radps,
    f_front,
    fx_front,
    fz_front,
    sf,
    steer_ratio,
    t0_m,
    tm_m,
    limit,
    mu_grid,
    temper,
    lk,
):
    """One sample with both torques: the likelihood over mu (lk, one value per grid mu, raised to `temper`; True
    returned) where the term speaks, then each hypothesis's gain updated with the sample. steer_rate_radps: the road
    wheels' steering rate; sf: the force per load's sd; limit: a controller acts or a wheel is past its peak."""
    fy = f_front * fz_front
    f_prev = mem[base + A_F_PREV]
    mem[base + A_F_PREV] = f_front
    if limit or not dt > 0.0 or abs(f_front) < CALIBRATION_MIN_F:
        return False
    friction = COLUMN_FRICTION_NM * tanh(steer_rate_radps * steer_ratio / FRICTION_RATE_RADPS)
    moment = steer_ratio * (driver_nm + eps_nm - friction)
    df = abs(f_front - f_prev) / dt * TIME_OFFSET_S
    var_col = 2.0 * (steer_ratio * TORQUE_NOISE_NM) ** 2 + (steer_ratio * COLUMN_FRICTION_SD_NM) ** 2
    var_f = (sf * sf + df * df) * fz_front * fz_front  # the force's error, times each hypothesis's trail below
    speak = abs(f_front) >= EVIDENCE_MIN_F and mem[base + A_W] >= CALIBRATED_S
    trail0 = t0_m + tm_m
    lam = exp(-dt / RLS_TAU_S)
    for i in range(mu_grid.size - 1, -1, -1):
        mu = mu_grid[i]
        mu_y = lateral_friction(mu, fx_front)
        x = abs(f_front) / mu_y
        if x >= 1.0:  # past this hypothesis's limit: the friction bound judges it, not the trail
            lk[i] = lk[i + 1] if i + 1 < mu_grid.size else 1.0
            continue
        b = base + A_CELLS + 2 * i
        g, p = mem[b], mem[b + 1]
        h = (t0_m * (1.0 - x) ** (1.0 / 3.0) + tm_m) * fy  # the moment at gain 1
        r = var_col + var_f * (g * h / fy) ** 2 + (MODEL_SHARE * g * (trail0 * fy - h)) ** 2
        if speak:
            lk[i] = exp(-0.5 * temper * (moment - g * h) ** 2 / (r + (p + (GAIN_FLOOR * g) ** 2) * h * h))
        if x <= CALIBRATION_MAX_X:  # recursive least squares with forgetting, never wider than the prior
            p = min(p / lam, GAIN_SD0**2)
            k = p * h / (h * h * p + r)
            mem[b] = min(max(g + k * (moment - g * h), GAIN_RANGE[0]), GAIN_RANGE[1])
            mem[b + 1] = p - k * h * p
    mem[base + A_W] += dt
    if speak:
        mem[base + A_USED] += 1.0
    return speak
