"""pmf's optional channels (CONTRACTS 3.1): the GNSS Doppler speed as a slip reference, the drive and brake forces as
each axle's force, and the slip slope against them (Gustafsson, "Slip-based tire-road friction estimation", Automatica
33(6), 1997). Compiled helpers that pmf's step calls; the likelihood's grid and its application stay pmf's.

The reference. A production car's speed comes from its wheels, so under braking (every wheel brakes) and with all-wheel
drive it has no slip-free reference. A GNSS receiver's Doppler speed (0.05 m/s, 10 Hz) is one, with latency (0-0.2 s),
outages (tunnels) and multipath outliers. A three-state Kalman filter tracks the speed over ground V, the receiver's
latency L and b, the accelerometer's error that pmf's calibration leaves (a grade changing along the road, a bias that
moved since; a random walk, its spread capped at the calibration's): V is predicted by a_x - b (a_x with pmf's
calibrated bias taken out; the accelerometer's own error beside b grows V's spread linearly, a systematic error, not
white), and a fix z describes V at t - L, z = V - (a_x - b) L, so L is identified where a_x changes (braking,
starting) and b where the fixes drift from the prediction, both kept across gaps (the receiver's and the road's).
Without b, V lagged the true speed on a grade the calibration had not seen (docs/ESTIMATORS.md 9).
A fix whose innovation lies beyond GATE_SIGMA of its predicted spread (the receiver's sAcc, GNSS_SD_DEFAULT_MPS where
it reports none) is rejected as an outlier; RELOCK_MISSES rejections in a row, or the spread past LOST_SD_MPS (an
outage), and the filter locks afresh on the next fix, which counts only after CONFIRM_FIXES agree. The reference is used
only while locked, confirmed and within REF_MAX_SD_MPS; otherwise pmf works from its base channels alone.

The slip. Each axle's speed is its wheels' mapped to the CoG by pmf's wheel kinematics (a turn's geometry taken out),
the reference is V's component along the body, sqrt(V^2 - v_y^2), v_y = r l_r - v alpha_r (the rear axle's kinematics,
as pmf's). s = v_axle / v_x - 1 carries the rolling radius's error (1 % of radius: 0.01 of slip, more than moderate
driving's whole slip), so each axle keeps a slip line s = s0 + k f by recursive least squares with forgetting (RLS_TAU_S)
over straight, calm driving (|f| < LINE_MAX_F): s0 is the radius calibrated against GNSS, k Gustafsson's slip slope
(1 / the axle's longitudinal stiffness per load). The line's intercept variance enters every slip term, counted once
over the grid's memory (the same error at every sample), so an axle not yet calibrated says nothing of mu.

The force. Each axle's force per load comes from the drive and brake force channels where the car sends them (the
drive force by the profile's drive split, the brake force by its brake balance; FORCE_SCALE_SD of scale error, the ECU's
torque model), else from m a_x allocated the same way (the accelerometer's remaining bias through the mass).

The evidence. The brush model's slip at the axle's force per load (lateral.py `brush_slip`, the same relation as pmf's
axle-slip term) against the measured slip minus s0, for every (mu, C) of pmf's grid; the spread is the reference's,
the wheels' (noise, a time offset against the accelerometer under deceleration), the force's through the line's
slope, and the brush model's error against real tires (a share of the prediction). Under braking where pmf's braking
term speaks, that term reads the wheels and this one is silent (`evidence` False). What it can prove
(docs/ESTIMATORS.md 9): at low utilization the brush slip is f / C whatever mu (its excess over the line is about
f / (3 mu)), so calm driving tells the stiffness, not mu; and the stiffness is the tire's and the surface's together
(Gustafsson's slope-mu correlation is empirical, per tire), so the slope is never mapped to mu directly: the grid
marginalises C, and only the bend of slip against force near the limit (braking, accelerating, where the wheels have
no reference of their own) narrows mu. The steering torques are aligning.py's (docs/ESTIMATORS.md 9).
"""

from __future__ import annotations

from math import exp, sqrt

import numpy as np
from numba import njit

from roadgrip.estimators.lateral import brush_slip
from roadgrip.units import G_MPS2

# The GNSS reference filter
GNSS_SD_DEFAULT_MPS = 0.1  # a fix without its receiver's accuracy: twice a u-blox's typical sAcc
GNSS_SD_FLOOR_MPS = 0.03  # sAcc is the receiver's own estimate; below this it is optimistic
LATENCY_PRIOR_S = 0.1  # the latency's prior: 0-0.2 s (uniform: mean 0.1, sd 0.058)
LATENCY_PRIOR_SD_S = 0.058
LATENCY_RANGE_S = (0.0, 0.4)
LATENCY_WALK_S_PER_SQRT_S = 0.001  # a receiver's latency barely changes
ACCEL_ERROR_MPS2 = 0.1  # the accelerometer's error beside the filter's b (as pmf's allowance): pitch, vibration
B_WALK_MPS2_PER_SQRT_S = 0.03  # how fast b moves: a grade changing along the road (1 % in about 10 s)
GATE_SIGMA = 4.0  # innovations beyond 4 sigma: multipath
RELOCK_MISSES = 10  # a second of rejected fixes in a row: the filter, not the fixes, is wrong
LOST_SD_MPS = 0.5  # an outage of a few seconds: lock afresh on the next fix
CONFIRM_FIXES = 3  # fixes after a fresh lock before the reference counts (the lock may have been an outlier)
REF_MAX_SD_MPS = 0.15  # the reference speaks for slip while known to this (0.75 % of slip at 20 m/s)
# The slip lines and the evidence
RLS_TAU_S = 120.0  # the slip line's memory (as pmf's front/rear line)
LINE_MAX_F = 0.15  # the line from calm driving: the brush slip within 6 % of f / C at mu >= 0.8
LINE_S0_SD0 = 0.03  # an uncalibrated axle: the radius +-2 % and its wear, the catalogue's nominal
LINE_K_SD0 = 0.5  # ... and its slope +-50 % of the profile's 1 / C
LINE_MAX_ACCEL_MPS2 = 3.0  # the line from samples where latency and time offsets leave little
EVIDENCE_MIN_F = 0.02  # below this force per load an axle's slip is its radius error and noise
EVIDENCE_MAX_AY_MPS2 = 1.5  # combined slip: a cornering axle slips more at the same force; its lateral share small
WHEEL_TIME_OFFSET_S = 0.05  # the wheel speeds and the accelerometer read up to 50 ms apart (pmf LAT_TIME_OFFSET_S)
FORCE_SCALE_SD = 0.05  # the drive and brake forces' scale: the ECU's torque model, the pads' friction
FORCE_NOISE_N = 100.0  # ... and their noise and lag (0.1 s) on a changing force
# Memory block (offsets from its start)
C_V, C_PVV, C_PVL, C_PLL, C_L, C_AGREE, C_MISS, C_OUTLIERS, C_LOCKED, C_A_PREV = range(10)
C_LINE = 10  # per axle (front, rear): s0, k, P00, P01, P11, seconds of data
L_S0, L_K, L_P00, L_P01, L_P11, L_W = range(6)
N_LINE = 6
N_CHANNEL_MEM = C_LINE + 2 * N_LINE
# The reference filter's accelerometer error state (its own block): b, its covariances with V and L, its variance
B_B, B_PVB, B_PLB, B_PBB = range(4)
N_BIAS_MEM = 4


@njit(cache=True)
def init_channel_memory(mem, base, c0_front, c0_rear):
    """The block's start: no lock, the latency's prior, each axle's line at the profile's stiffness."""
    for k in range(N_CHANNEL_MEM):
        mem[base + k] = 0.0
    mem[base + C_L] = LATENCY_PRIOR_S
    mem[base + C_PLL] = LATENCY_PRIOR_SD_S**2
    for axle in range(2):
        b = base + C_LINE + axle * N_LINE
        c0 = c0_front if axle == 0 else c0_rear
        mem[b + L_K] = 1.0 / c0
        mem[b + L_P00] = LINE_S0_SD0**2
        mem[b + L_P11] = (LINE_K_SD0 / c0) ** 2


@njit(cache=True)
def init_bias_memory(mem, bias_base, sd0):
    """The reference filter's accelerometer error state (its own block, appended after the first): none known yet,
    within sd0, the uncalibrated accelerometer's spread (capped at pmf's calibration's as soon as the filter
    predicts)."""
    mem[bias_base + B_B] = 0.0
    mem[bias_base + B_PVB] = 0.0
    mem[bias_base + B_PLB] = 0.0
    mem[bias_base + B_PBB] = sd0 * sd0


@njit(cache=True)
def unlock(mem, base):
    """The reference lost (a gap in the data): it speaks again only after a fresh lock and CONFIRM_FIXES agreeing
    fixes. The latency and b are kept (the receiver's and the road's)."""
    mem[base + C_LOCKED] = 0.0
    mem[base + C_AGREE] = 0.0
    mem[base + C_MISS] = 0.0


@njit(cache=True)
def _lock(mem, base, bias_base, z, a, r):
    """A fresh lock on the fix z: V = z + (a - b) L, its covariance with L and b from theirs (L and b are kept: the
    receiver's and the road's)."""
    a_c = a - mem[bias_base + B_B]
    lat = mem[base + C_L]
    pll, plb, pbb = mem[base + C_PLL], mem[bias_base + B_PLB], mem[bias_base + B_PBB]
    mem[base + C_V] = z + a_c * lat
    mem[base + C_PVV] = r + a_c * a_c * pll + lat * lat * pbb - 2.0 * a_c * lat * plb
    mem[base + C_PVL] = a_c * pll - lat * plb
    mem[bias_base + B_PVB] = a_c * plb - lat * pbb
    mem[base + C_AGREE] = 0.0
    mem[base + C_MISS] = 0.0
    mem[base + C_LOCKED] = 1.0


@njit(cache=True)
def gnss_update(mem, base, bias_base, z, accuracy, a, bias_sd, dt):
    """Predict the speed over ground V with the accelerometer's a (pmf's calibrated bias out) less the filter's own
    estimate b of what remains (a grade, a bias drifting since calibration) over dt, then take the fix z (NaN: none)
    with its reported accuracy (NaN: not reported). b's spread never exceeds pmf's calibration's, bias_sd. Fixes below
    0.5 m/s say nothing of the direction of travel: skipped."""
    locked = mem[base + C_LOCKED] > 0.0
    # z = V - a L holds where a was constant over the last L: where it changed, the fix's model is uncertain by the
    # change times the latency (the onset of braking would otherwise be read as latency, and then gated away)
    a_change = a - mem[base + C_A_PREV] if dt > 0.0 else 0.0
    mem[base + C_A_PREV] = a
    if dt > 0.0:
        pbb = mem[bias_base + B_PBB] + B_WALK_MPS2_PER_SQRT_S**2 * dt
        if pbb > bias_sd * bias_sd:  # b scaled to pmf's spread, D P D with D = diag(1, 1, scale): P stays positive
            scale = bias_sd / sqrt(pbb)
            mem[bias_base + B_PVB] *= scale
            mem[bias_base + B_PLB] *= scale
            pbb = bias_sd * bias_sd
        mem[bias_base + B_PBB] = pbb
        mem[base + C_PLL] += LATENCY_WALK_S_PER_SQRT_S**2 * dt
    if locked and dt > 0.0:
        # x = (V, L, b): V += (a - b) dt; F = [[1, 0, -dt], [0, 1, 0], [0, 0, 1]]
        mem[base + C_V] += (a - mem[bias_base + B_B]) * dt
        pvb, pbb = mem[bias_base + B_PVB], mem[bias_base + B_PBB]
        # b's part through F; the accelerometer's own error beside it (pitch under braking, vibration) as a
        # systematic one: V's spread grows linearly by it
        pvv = mem[base + C_PVV] - 2.0 * dt * pvb + dt * dt * pbb
        mem[base + C_PVV] = (sqrt(max(pvv, 0.0)) + ACCEL_ERROR_MPS2 * dt) ** 2
        mem[base + C_PVL] -= dt * mem[bias_base + B_PLB]
        mem[bias_base + B_PVB] = pvb - dt * pbb
        if mem[base + C_PVV] > LOST_SD_MPS**2:
            mem[base + C_LOCKED] = 0.0
            locked = False
    if not np.isfinite(z) or z < 0.5:
        return
    sd_z = accuracy if np.isfinite(accuracy) and accuracy > 0.0 else GNSS_SD_DEFAULT_MPS
    r = max(sd_z, GNSS_SD_FLOOR_MPS) ** 2 + (a_change * LATENCY_RANGE_S[1]) ** 2
    if not locked:
        _lock(mem, base, bias_base, z, a, r)
        return
    # z = V - (a - b) L: H = (1, -(a - b), L)
    a_c = a - mem[bias_base + B_B]
    lat = mem[base + C_L]
    pvv, pvl, pll = mem[base + C_PVV], mem[base + C_PVL], mem[base + C_PLL]
    pvb, plb, pbb = mem[bias_base + B_PVB], mem[bias_base + B_PLB], mem[bias_base + B_PBB]
    y = z - (mem[base + C_V] - a_c * lat)
    ph0 = pvv - a_c * pvl + lat * pvb
    ph1 = pvl - a_c * pll + lat * plb
    ph2 = pvb - a_c * plb + lat * pbb
    s = ph0 - a_c * ph1 + lat * ph2 + r
    if y * y > GATE_SIGMA * GATE_SIGMA * s:
        mem[base + C_OUTLIERS] += 1.0
        mem[base + C_MISS] += 1.0
        if mem[base + C_MISS] >= RELOCK_MISSES:
            _lock(mem, base, bias_base, z, a, r)
        return
    k0, k1, k2 = ph0 / s, ph1 / s, ph2 / s
    mem[base + C_V] += k0 * y
    mem[base + C_L] = min(max(lat + k1 * y, LATENCY_RANGE_S[0]), LATENCY_RANGE_S[1])
    mem[bias_base + B_B] += k2 * y
    mem[base + C_PVV] = pvv - k0 * ph0
    mem[base + C_PVL] = pvl - k0 * ph1
    mem[base + C_PLL] = pll - k1 * ph1
    mem[bias_base + B_PVB] = pvb - k0 * ph2
    mem[bias_base + B_PLB] = plb - k1 * ph2
    mem[bias_base + B_PBB] = pbb - k2 * ph2
    mem[base + C_MISS] = 0.0
    mem[base + C_AGREE] += 1.0


@njit(cache=True)
def reference_speed(mem, base, yaw_rate, lr, v, aty, ca_rear):
    """(v_x, its sd): the GNSS reference along the body at the CoG, or (nan, nan) where it does not speak."""
    if mem[base + C_LOCKED] == 0.0 or mem[base + C_AGREE] < CONFIRM_FIXES or mem[base + C_PVV] > REF_MAX_SD_MPS**2:
        return np.nan, np.nan
    vy = yaw_rate * lr - v * aty / (G_MPS2 * ca_rear)
    ground = mem[base + C_V]
    return sqrt(max(ground * ground - vy * vy, 0.0)), sqrt(mem[base + C_PVV])


@njit(cache=True)
def axle_forces(out, drive_n, brake_n, m, atx, accel_sd, fz_front, fz_rear, front_drive, brake_front, frr):
    """Each axle's longitudinal force per load (out[0] front, out[1] rear) and its sd (out[2], out[3]): from the drive
    and brake force channels where both are sent (True returned), else from m a_x (atx: the road's force per mass,
    accel_sd its error) allocated by the profile's brake balance (braking) or drive split (driving; a two-wheel drive's
    undriven axle only rolls, its rolling resistance borne by the driven one)."""
    if np.isfinite(drive_n) and np.isfinite(brake_n):
        f_front = front_drive * drive_n - brake_front * brake_n
        f_rear = (1.0 - front_drive) * drive_n - (1.0 - brake_front) * brake_n
        out[0], out[1] = f_front / fz_front, f_rear / fz_rear
        out[2] = (FORCE_SCALE_SD * abs(f_front) + FORCE_NOISE_N) / fz_front
        out[3] = (FORCE_SCALE_SD * abs(f_rear) + FORCE_NOISE_N) / fz_rear
        return True
    total = m * atx
    share = brake_front if atx < 0.0 else front_drive
    f_front, f_rear = share * total, (1.0 - share) * total
    if atx >= 0.0 and front_drive == 1.0:
        f_front, f_rear = total + frr * fz_rear, -frr * fz_rear
    elif atx >= 0.0 and front_drive == 0.0:
        f_front, f_rear = -frr * fz_front, total + frr * fz_front
    out[0], out[1] = f_front / fz_front, f_rear / fz_rear
    out[2] = max(share, 0.5) * m * accel_sd / fz_front
    out[3] = max(1.0 - share, 0.5) * m * accel_sd / fz_rear
    return False


@njit(cache=True)
def axle_slip_evidence(
    mem,
    base,
    axle,
    dt,
    f,
    f_sd,
    v_axle,
    v_ref,
    v_ref_sd,
    ax,
    calm,
    evidence,
    s_floor,
    model_share,
    c0,
    mu_grid,
    c_factors,
    temper,
    repeats,
    like,
):
    """One axle's slip against the GNSS reference: the likelihood over pmf's (mu, C) grid into `like` (True returned)
    where `evidence`, then the axle's slip line updated where `calm` (straight, calm driving)."""
    b = base + C_LINE + axle * N_LINE
    s = v_axle / v_ref - 1.0
    v = v_ref
    var_meas = (v_ref_sd / v) ** 2 + (abs(ax) * WHEEL_TIME_OFFSET_S / v) ** 2 + s_floor * s_floor
    used = False
    if evidence and abs(f) >= EVIDENCE_MIN_F:
        s_meas = s - mem[b + L_S0]
        # the line's intercept is the same at every sample within the grid's memory: its variance counts `repeats`
        # times, so that it counts once (the reference's error is correlated over the filter's few fixes, as TEMPER)
        sd0 = sqrt(var_meas + repeats * mem[b + L_P00] + (f_sd * mem[b + L_K]) ** 2)
        for i in range(mu_grid.size):
            shape = brush_slip(f, mu_grid[i], c0)  # at C = c0; at C it is shape / C
            for j in range(c_factors.size):
                pred = shape / c_factors[j]
                sig = sd0 + model_share * abs(pred)
                like[i, j] = exp(-0.5 * temper * ((s_meas - pred) / sig) ** 2)
        used = True
    if calm and dt > 0.0 and abs(f) < LINE_MAX_F and abs(ax) < LINE_MAX_ACCEL_MPS2:
        lam = exp(-dt / RLS_TAU_S)
        p00, p01, p11 = mem[b + L_P00] / lam, mem[b + L_P01] / lam, mem[b + L_P11] / lam
        p00 = min(p00, LINE_S0_SD0**2)  # no wind-up past the prior on a long cruise at constant force
        ph0, ph1 = p00 + p01 * f, p01 + p11 * f
        den = ph0 + ph1 * f + var_meas + (f_sd * mem[b + L_K]) ** 2
        k0, k1 = ph0 / den, ph1 / den
        err = s - (mem[b + L_S0] + mem[b + L_K] * f)
        mem[b + L_S0] += k0 * err
        mem[b + L_K] += k1 * err
        mem[b + L_P00] = p00 - k0 * ph0
        mem[b + L_P01] = p01 - k0 * ph1
        mem[b + L_P11] = p11 - k1 * ph1
        mem[b + L_W] += dt
    return used
