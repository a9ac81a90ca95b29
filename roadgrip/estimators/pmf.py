"""A Bayesian grid (point-mass) filter over mu and the tire's slip stiffness, from the evidence production cars send.

Production terminals compute their speed from the wheel speeds, so the speed carries no slip; their accelerometers carry
bias and road grade; their tires are worn and of unknown stiffness. This estimator uses only what such a car proves:

| evidence | when | likelihood of (mu, C) |
|---|---|---|
| the friction bound | a utilisation above the largest recent one | P(mu >= u) = Phi((mu - u) / s_u), u = |a_road| / g (guard.py), s_u the accelerometer's noise and its remaining bias; plus the chance that the driver asked for more than mu and the tires saturated (`_demand_likelihood`) |
| at the friction limit | ABS, TCS or ESC active | ABS: the force per load it holds, the brush force at its slip band (0.06-0.15; near the peak for a stiff tire, below it for a soft one), lies between u_car = u (both axles at their limit) and u_first, the utilisation of the axle the profile's brake_front_share saturates first (only that one at its limit; the pedal is not sent, so anything between), u_first blurred by the load share's spread too (`_abs_likelihood`); traction control: u_axle, the driven axle's force per load, the brush force at some slip in its band (0.02-0.1; `_tcs_likelihood`), blurred as u_first; ESC's engine cut: u / mu anywhere above 0.1 |
| a wheel locked or spinning | a wheel's slip against its kinematic speed at the reference speed beyond LOCK_SLIP, v_ref >= SLIP_MIN_SPEED_MPS | u / mu in [ETA_LOCK, 1] |
| slip between driven and undriven axles | 2WD, driving (not braking), straight, v >= SLIP_MIN_SPEED_MPS, no controller or wheel past its peak (the limit terms read those wheels) | N(s; s_brush(f, mu, C), s_s): the brush model's slip at the driven axle's force per load f |
| slip between front and rear axles under braking | every drive, braking at BRAKE_MIN_MPS2 or more without a controller or a wheel past its peak, straight, v >= SLIP_MIN_SPEED_MPS, the front/rear zero calibrated | N(d; line(x) + s_brush(f_f, mu, C) - s_brush(f_r, mu, C) - the static line, s_d): each axle's force per load by the profile's brake_front_share, the car's braking line learned in gentle stops; before it is, the brush slips alone, the split's and load share's error counted once (`_brake_slip_likelihood`) |
| the understeer angle delta - L r / v | v >= SLIP_MIN_SPEED_MPS, no ABS, no wheel past its peak, |a_x| under BRAKE_MIN_MPS2, road-wheel angle under LAT_MAX_STEER_RAD | N(delta - L r / v - b; k_f alpha_f - k_r alpha_r + e L r / v, s_a): the brush model's slip angles at each axle's lateral force per load (lateral.py), the tires' compliances (k_f, k_r) and the kinematic angle's scale error e a Gaussian state marginalised (its predictive density), one-sided where an axle is at its limit |
| the front axle's aligning moment (both steering torques sent) | its gain calibrated (aligning.py), |f_front| >= 0.05, no controller, no wheel past its peak, v >= ALIGNING_MIN_SPEED_MPS (2 m/s: walking-pace turns included) | N(n T; g (t0 (1 - f / mu)^(1/3) + t_m) F_y,f, s_M): the brush model's pneumatic trail at the front axle's force, each mu with its own calibrated gain g |

with C the longitudinal slip stiffness per load (N per unit slip per N), carried on the grid as a factor of the
profile's and marginalised out, so that an unknown tire widens the posterior rather than biasing it. The brush model
(Pacejka, Tyre and Vehicle Dynamics, 3rd ed., section 3.2) gives, for a tire of stiffness C at utilisation f / mu,

    s = (3 mu / C) (1 - (1 - f / mu)^(1/3))          (f < mu; s = f / C at small f, whatever mu)

so slip at small force tells C, and slip growing faster than f / C tells mu. The likelihoods that every sample of a
steady manoeuvre repeats (controllers, slip) are tempered (raised to TEMPER), because consecutive 100 ms samples share
their errors (model error, bias); the bound is a maximum and is applied only where a sample raises it.

Between samples mu diffuses (random walk, a 3-tap kernel whose moves are accepted against the prior, Metropolis: it
leaves the prior as it is) and the grid is mixed with the prior at FORGET_PER_S while the car moves (both in proportion
to the speed below FORGET_MOVING_MPS) and slowly in place (FORGET_STILL_PER_S: weather): evidence ages, so that a car
leaving a braking zone does not carry its mu onto the next road, a car standing on the ice it braked on keeps knowing
it, and with no evidence the posterior returns to the prior. The prior (PRIOR) is half dry asphalt (normal, 0.85 +-
0.15) and half spread evenly over 0.1-1.1: below excitation the answer is this wide interval, never a low number.

Self-calibration, kept in the state (so the cloud keeps it per vehicle through state_to_dict):
- the accelerometer's bias: a slow average (BIAS_TAU_S of steady driving) of a_x - dv/dt, dv/dt from the wheels;
  a_road uses a_x minus it, and s_u shrinks from BIAS_SIGMA0 towards BIAS_SIGMA_FLOOR (grades that vary) as it settles;
- the left/right rolling-radius ratio of each axle, from straight driving, each wheel against its kinematic speed
  (RADIUS_TAU_S);
- the front/rear radius mismatch and the slip slope 1/C at low force: a recursive least-squares line s = s0 + f / C
  over free rolling and gentle driving (RLS_TAU_S forgetting); s0 is taken out of the measured slip, and once the line
  has STIFFNESS_CALIBRATED_S of data the grid's stiffness marginal (kept across gaps) forgets towards its 1 / slope;
- the braking term's zero: an AWD's front/rear rolling-radius ratio (a 2WD's is the slip line's s0, above), the mean
  of v_front / v_rear - 1 (speeds mapped to the CoG) over straight calm driving (|a_road| under FR_CALM_MPS2), its
  running mean until RADIUS_TAU_S of it, then a moving average over that span; read once it has FR_CALIBRATED_S;
- the braking line d = b + k_b x (x the brakes' force per weight at the static loads; k_b the car's own split, load
  share and tires in one number, b what the zero leaves): recursive least squares over gentle straight stops (x under
  BRAKE_LINE_MAX_G) on x and d filtered over SLIP_LINE_FILTER_S, fed only once a stop has held those conditions
  LINE_SETTLE_S (not its onset), from the catalogue's k_b and b = 0 +- BRAKE_ZERO_SIGMA; once it has
  BRAKE_LINE_CALIBRATED_S of them the braking term reads only the slip beyond it;
- the lateral accelerometer's bias: a slow average (BIAS_TAU_S) of a_y - v r over straight driving (its mounting roll;
  a road's crossfall, which the tires do carry, is taken with it: documented in docs/PRODUCTION.md);
- the understeer line delta - L r / v = b + k x0 (x0 = f_f / c_f - f_r / c_r at the profile's cornering stiffnesses per
  load; b the steering and gyro offsets, k the tires' compliance over the profile's, K_us = k (1 / c_f - 1 / c_r) / g):
  recursive least squares (RLS_TAU_S) over calm driving only, where the brush model is within 10 % of its line (|a_y|
  under LAT_CALM_SHARE of the proven friction and LAT_CALM_AY_MPS2, and the yaw rate within LAT_REF_AGREE of the
  steer's linear reference r_ref = v delta / (L + K_us v^2)); the lateral term takes its offset b (the covariance's
  b part as noise), and the reference its K_us. Each restart (`_start`: a gap or a
  new segment, perhaps a new power-on) returns the offset's covariance to an uncalibrated car's (LAT_OFFSET_SIGMA0_RAD)
  and keeps the slope: a MEMS gyro's bias comes back different at each power-on, so a new trip's offset is learned in
  its first seconds of calm driving instead of being read as the tires' slip angles (docs/RESULTS.md, "A new trip's
  gyro bias").

The tires' cornering compliances over the profile's (k_f, k_r: 1 +- LAT_SLOPE_SIGMA0 common, +- LAT_AXLE_SIGMA each
axle's own) are a state the samples share, not noise each sample has: given mu the understeer angle is linear in them,
so the state carries their Gaussian; at each sample every grid mu's Kalman update with the angle is collapsed into
one pair again (weighted by the posterior over mu: the tires are the car's, whatever the road), and between samples
the pair forgets towards the prior at C_FORGET_PER_S. The term speaks from a new car's first
sample, its likelihood the predictive density, so a compliance the angle has not yet pinned down widens it once
rather than at every sample (docs/ESTIMATORS.md 11). The same Gaussian carries the kinematic angle's scale error
(0 +- LAT_KINEMATIC_SIGMA: the profile's wheelbase and steering ratio, the wheels' radius in v): in a tight turn at
walking pace the kinematic angle L r / v is 20 times the tires' slip angles, and a few percent of it, read as the
tires', was a dry or wet turn read as ice.

The lateral channel needs no steady state: the understeer angle alpha_f - alpha_r = delta - L r / v is kinematic (v_y
cancels) and the axles' forces come from a_y and the yaw acceleration (Newton-Euler), so a sine steer is read as a ramp
is. What a transient leaves is timing: the steering, IMU and wheel groups read up to LAT_TIME_OFFSET_S apart and the
tire's force lags its slip angle by its relaxation length over v, so the term's noise grows with the steering and yaw
rates times that lag. Not modelled (the term then errs): a large roll steer or compliance steer beyond the calibrated
line's, and a banked turn's road-plane geometry (the accelerometer reads the tires' force, which is what the term needs,
but the lateral bias calibration takes a long crossfall for bias).

An evidence term that no cell of the grid explains (its total likelihood below INCONSISTENT of its best) is an
inconsistency of the model with the measurement: it is skipped and counted, never read as low friction. The axle-slip
term is judged against the stiffness alone (`_apply_at_stiffness`: no mu explains it at the C marginal): mu jumps at a
patch's edge, the tire's stiffness does not, and against the posterior of the road behind, the slip of the first
metres on ice read as an inconsistency (a TCS pass on mu 0.21 skipped it at 59 of its 60 saturated samples).
The estimate: mu the posterior median, the 90 % interval its 5 % and 95 % quantiles with both ends widened to every mu
the evidence does not exclude (the likelihood-ratio interval of the evidence alone, `_evidence_interval`: the prior
is about roads in general, so its low tail excludes the car that is on ice and its high tail the best dry asphalt;
where the evidence is silent the ends are the grid's lowest cell and PRIOR_UPPER_MU), excited where the sample's own utilisation u / mu is at least 0.5 (CONTRACTS 4),
a controller acts, or the posterior's own interval is narrower than EXCITED_WIDTH.

Kinematics before slip: in a turn the wheels roll at different speeds without slipping (the outer faster than the
inner by track / R, 17 % at R = 10 m; the front axle on a larger radius than the rear). Every slip term first takes out
what the car's motion explains: `wheel_kinematics` gives the speed along its heading at which each wheel rolls freely,
as an affine function of the CoG's speed v, from the yaw rate, the half-tracks, the axle positions, the steer angle
delta = steering_wheel_angle / steering_ratio (ISO 8855, positive left) and the rear tires' slip angle; each wheel's
measured speed is mapped back to the CoG through it, and a wheel's slip is (omega_i R_i - v_wheel_i) / max(|.|) against
its own kinematic speed at the reference speed. The reference speed, the axle slip and the left/right radius
calibration all use the mapped speeds. Below SLIP_MIN_SPEED_MPS no slip term speaks (the wheel-speed resolution is too
large a share of v); the bound and the controllers' flags speak at every speed, ABS's slip band included (it is the
flag's reading, not a measured slip).

The reference speed is what an ABS controller keeps (Bosch, Automotive Handbook, "Antilock braking system"): the wheels'
own (mapped to the CoG) while they agree; otherwise the fastest wheel (the slowest while driving), changing no faster
than the accelerometer's a_x allows, so that locked or spinning wheels do not drag it along; a wheel far from it is past
its friction peak. Where the tires work hard (the recent largest utilisation at least half the median, or an axle at a
controller's limit) the interval's lower end reaches that utilisation: the truth may lie right at the proven bound.

Size: over 500 lines because one filter: its evidence terms share the grid, the state and the compiled update loop; the
docstring is its derivation.
"""

from __future__ import annotations

from math import cos, exp, sin, sqrt
from operator import itemgetter

import numpy as np
import pyarrow as pa
from numba import njit

from roadgrip.estimators import aligning as al
from roadgrip.estimators import slip_slope as ch
from roadgrip.estimators.base import (
    Estimate,
    EstimateRun,
    Estimator,
    estimate_table,
    memory_state,
    profile_of_call,
)
from roadgrip.estimators.guard import PRIOR_UPPER_MU, drag_per_mass
from roadgrip.estimators.lateral import (
    N_COMPLIANCE,
    N_LATERAL_PARAMS,
    axle_lateral_per_load,
    brush_slip,
    brush_slip_angle_slope,
    lateral_likelihood,
    normal_cdf,
    pack_gaussian,
    reference_yaw_rate,
    understeer_gradient,
    unpack_gaussian,
)
from roadgrip.estimators.vehicle_model import roll_per_lateral_accel
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import VehicleParams

MU_GRID = np.round(np.arange(0.05, 1.5001, 0.025), 4)  # the grid's mu values
C_FACTORS = np.geomspace(0.2, 2.0, 11)  # slip stiffness per the profile's: tire and surface (cobblestone: 0.3)
NM, NC = MU_GRID.size, C_FACTORS.size


def _prior(mu):
    dry = np.exp(-0.5 * ((mu - 0.85) / 0.15) ** 2) / (0.15 * np.sqrt(2 * np.pi))
    spread = ((mu >= 0.1) & (mu <= 1.1)).astype(float)  # a density of 1 over the 1.0 wide band
    p = 0.5 * dry + 0.5 * spread + 1e-3
    return p / p.sum()


PRIOR = _prior(MU_GRID)
# The random walk's moves up and down the grid, accepted as Metropolis accepts them against PRIOR (min(1, PRIOR[to] /
# PRIOR[from])): the walk then leaves the prior as it is (detailed balance), so that posterior / prior, which the
# interval's ends read (`_evidence_interval`), moves only with evidence, not with the walk's spreading into the
# prior's thin tail above 1.1
WALK_UP = np.append(np.minimum(1.0, PRIOR[1:] / PRIOR[:-1]), 0.0)
WALK_DOWN = np.insert(np.minimum(1.0, PRIOR[:-1] / PRIOR[1:]), 0, 0.0)
C_PRIOR = np.exp(-0.5 * (np.log(C_FACTORS) / 0.6) ** 2)  # around the profile's, broad: worn tires, soft surfaces
C_PRIOR /= C_PRIOR.sum()

# Tuning, each with its reason
TEMPER = 0.3  # 10 Hz samples: errors correlated over about 0.3 s (ABS cycle, suspension, signal offsets)
FORGET_PER_S = 0.3  # evidence halves in about 2.3 s: 50 m at 80 km/h, under an H3 cell of the map
MU_WALK_PER_SQRT_S = 0.05  # the road's mu changing along the path
# ... while the car moves: below this speed (creeping, queueing, standing) it stays on the same metres, and both scale
# down with the speed (per metre as at this speed: halves in 12 m), so a car standing on the ice it braked on keeps
# knowing it
FORGET_MOVING_MPS = 5.0
FORGET_STILL_PER_S = 1.0 / 3600.0  # the road's own change in place (weather, salt, thaw): within the hour
C_FORGET_PER_S = 1.0 / 120.0  # the slope is the tire's and the surface's (Gustafsson 1997): it changes with the road
# What a controller's activity says of the acting axle's utilisation u_axle / mu. Both controllers of the simulator (and
# many production ones) act on slip thresholds, which a tire with a soft slip curve (cobblestone, winter tires) crosses
# below its peak: measured on the training and held-out runs of the generalization preset (5-95 %), ABS 0.86-1.0 and
# 0.57-1.0, traction control 0.48-0.99 and 0.22-0.87; on the physics validation split's tires of 0.3-0.45 of the
# catalogue's stiffness traction control held 0.07-0.12. So ABS and traction control are read through the tire's slip
# curve at their slip bands, with the grid's stiffness
ABS_SLIP_BAND = (0.06, 0.15)  # ABS cycles the slip between about 0.08 and 0.12 (Bosch; the simulator: 0.08/0.12)
ABS_BAND_POINTS = 5  # the slip band's force read at this many slips (midpoint rule): 1 % of mu apart on a stiff tire
# A catalogue profile does not know the car's load: ECE R13-H's laden and unladen conditions (a driver alone against
# the permissible maximum mass) move a car's static front load share by about 0.05
LOAD_SHARE_SPREAD = 0.05
LIMIT_PEAK_S = 1.0  # how long a controller's flag may lag or latch behind the utilisation it reacted to
# Traction control holds the driven wheels' slip in a band (the simulator: cut above 0.05, restore below 0.02;
# production systems up to about 0.1): the driven axle's force is the tire's at a slip there, near the peak for a stiff
# tire and a fraction of it for a soft one
TCS_SLIP_BAND = (0.02, 0.10)
# ESC's engine cut: the body's sideslip past its threshold (the simulator: 3 degrees beyond the kinematic, restored
# below 2), which a tire of 0.3 of the profile's cornering stiffness reaches at a fifth of a dry road's limit
ETA_ESC = 0.1
LIMIT_ESC, LIMIT_LOCK = 1, 2
DEMAND_G = 0.15  # everyday drivers ask for 0.15 g on average, rarely more than 0.3 g (naturalistic driving studies)
ETA_LIMIT = 0.8  # a car at its limit without a controller: u / mu 0.76-1.07 in the simulator (5-95 %, wheels locked)
ETA_LOCK = 0.7  # a locked or spinning wheel slides: sliding friction is 0.7-1 of the peak (Burckhardt's surfaces)
LOCK_SLIP = 0.15  # a wheel this far from the reference speed is past its peak (ABS thresholds: 0.1-0.2)
REF_AGREE = 0.03  # wheels within 3 % of each other roll freely: the reference speed is theirs (radius spread 2 %)
REF_TOLERANCE_MPS2 = 0.5  # the reference speed follows the wheels unless they change faster than a_x by this much
ACCEL_NOISE_MPS2 = 0.1  # per-sample accelerometer noise allowance (the simulator: 0.05 white)
BIAS_SIGMA0_MPS2 = 0.5  # an uncalibrated bias: mounting and pitch (a production SUV: -0.63 against d(speed)/dt)
BIAS_SIGMA_FLOOR_MPS2 = 0.15  # what calibration leaves: grades that vary along the road (1.5 %)
BIAS_TAU_S = 60.0  # seconds of steady driving after which the bias is known to BIAS_SIGMA_FLOOR_MPS2
# The bias average's window grows from BIAS_TAU_S with the steady driving seen, up to this: a_x - dv/dt is the
# sensor's bias plus g sin(grade), and the grade's part is tire force (the car climbs), so the average must span many
# roads' grades to leave the sensor's alone; over one road (BIAS_TAU_S) it takes that road's grade out of every force
# it reads, and the slip line's slope, regressed on those forces, comes out stiff (errors in the regressor)
BIAS_AVERAGE_S = 1200.0
RADIUS_TAU_S = 30.0  # seconds of straight driving that the left/right radius ratios span
RLS_TAU_S = 120.0  # the slip line's memory
# The slip line is regressed on the force and slip averaged over this (a first-order filter): the accelerometer's
# white noise (ACCEL_NOISE_MPS2, 0.01-0.02 of a wheel load) is as large as the force's own spread in steady driving, and
# noise in the regressor flattens the fitted slope (errors in variables: a sedan's 1 / C came out 0.019 against its
# tire's 0.062 on the fleet benchmark); over 1 s its variance falls 20-fold while the driver's changes of force, over
# seconds, pass
SLIP_LINE_FILTER_S = 1.0
# The braking line is fed only once a stop has held its conditions this long without a break: a stop's onset (the body
# pitching, about half a second at a pitch frequency of 1-1.5 Hz; the signal groups read up to 50 ms apart, so that
# one sample mixes the force before and after a step) does not lie on the line, and a driver who brakes firmly passes
# through gentle braking only there: a fleet car's braking line learned from such onsets and from a stop's release on
# an ice patch (k_b ten times the catalogue's) read every firm stop on dry asphalt as ice (mu_upper 0.44). The slip
# line is fed from its first sample: a trip starts in calm driving, and its intercept (the axles' radius mismatch,
# which the axle-slip term takes out) is wanted from the first seconds
LINE_SETTLE_S = 0.5
STIFFNESS_CALIBRATED_S = 30.0  # seconds of low-force driving before the slip line's slope informs the stiffness
STIFFNESS_SURFACE_SPREAD = 0.25  # what the slope at low force leaves unknown of the curve nearer the peak (log)
SLIP_SIGMA0 = 0.0015  # slip noise floor: wheel-speed noise, CAN quantisation, signal time offsets
SLIP_SIGMA_PER_MPS = 0.01  # ... growing at low speed (quantisation of 0.01 km/h over v)
SLIP_MODEL_SHARE = 0.25  # brush model error against real tires (Dugoff, Magic Formula, Burckhardt in the simulator)
# Slip is evidence from this speed on, for every slip term (a wheel past its peak, the axle slip, the radius ratios and
# the slip line); the bound and the controllers' flags speak at every speed. A wheel speed's error is absolute, so its
# share of v grows as v falls: one edge of a 48-tooth tone wheel counted in a 100 ms sample is 2 pi R / 4.8 = 0.39-0.50
# m/s (R 0.30-0.38 m), 8-10 % of 5 m/s, so two wheels a count apart either way reach LOCK_SLIP; and the noise term
# SLIP_SIGMA_PER_MPS / v (CAN resolution, tone-wheel jitter) is 0.002 at 5 m/s, the brush slip of gentle driving
# (f = 0.05 at C = 25), which the axle slip term needs to see. Parking, junctions and roundabouts lie mostly below.
SLIP_MIN_SPEED_MPS = 5.0
# The steering torques' term reads no wheel speed: its force is a_y's and the yaw acceleration's, its moment the
# column's, and the brush model's trail holds for a rolling tire at any speed at which its force settles within the
# turn (the relaxation length 0.6 m: 0.3 s at 2 m/s); below it a wheel that steers turns more about its vertical axis
# than it rolls (the parking torque). Junctions and roundabouts at walking pace (3-5 m/s) lie above.
ALIGNING_MIN_SPEED_MPS = 2.0
# Braking without a controller: every wheel brakes, so no axle is a reference, but the fixed brake split loads the axles
# unequally (brake_front_share against the front's load share) and the axle nearer its limit slips faster than its
# force (the brush curve), so the slip between front and rear axles tells mu where the tire's stiffness is known.
# From this deceleration on the brakes carry the force: an engine's overrun drag in gear is 0.2-0.4 m/s^2, on the
# driven axle alone, which the fixed split does not describe
BRAKE_MIN_MPS2 = 0.8
BRAKE_SHARE_SPREAD = 0.05  # the real split against the catalogue's: each axle's pad friction +-10 % (heat, wear)
# The braking term's zero: the front/rear radius ratio at no force. A 2WD car's is the slip line's intercept s0; an
# AWD's axles share the force near their load shares, so their slips differ by a fraction of f / C in calm driving
# (under 0.1 % at 0.05 g, C 20), and the ratio is the mean over straight driving below this force per mass
FR_CALM_MPS2 = 0.5
FR_CALIBRATED_S = 10.0  # seconds of that driving after which the zero is read
# The braking line: in gentle braking both axles are linear, so d = b + k_b x (x the brakes' force per weight, at
# the static loads) with k_b = (share / psi) / C_f - ((1 - share) / (1 - psi)) / C_r, the car's own split, load share
# and tires in one number, and b what the zero leaves (the slip line's intercept carries the driven axle's rolling
# resistance and its regression's error: 0.002-0.005 between a car's FWD and RWD variants). Learned per car by
# recursive least squares (RLS_TAU_S of braking) on x and d filtered over SLIP_LINE_FILTER_S (x's noise is a quarter
# to a half of its spread here), from the catalogue's k_b and b = 0 +- BRAKE_ZERO_SIGMA; it takes the split's and the
# load share's error out of the linear part, and the term reads only the slip the line does not explain. Below
# BRAKE_LINE_MAX_G a road of mu 0.4 or more leaves the front axle at about half its limit or less; a gentle stop on
# ice is read into the line too, and the line's memory of braking seconds keeps it one stop among many
BRAKE_LINE_MAX_G = 0.15
BRAKE_ZERO_SIGMA = 0.005
BRAKE_LINE_CALIBRATED_S = 5.0  # seconds of gentle braking after which the line replaces the catalogue's
# The lateral channel (lateral.py: the single-track model and the brush model's slip angles)
LAT_STEER_NOISE_RAD = 0.0035  # steering-wheel angle noise: 0.2 degrees (production angle sensors step 0.1 degrees)
LAT_YAW_NOISE_RADPS = 0.002  # a MEMS gyro's noise, about 0.1 degrees/s
LAT_TIME_OFFSET_S = 0.05  # the steering, IMU and wheel CAN groups are read up to 50 ms apart
LAT_RELAXATION_M = 0.6  # a tire's lateral relaxation length (Pacejka ch. 7: 0.3-1 m): its force lags by this / v
LAT_MAX_STEER_RAD = 0.15  # the single-track model's small angles: cos delta within 1.1 %, tan within 0.8 %
LAT_OFFSET_SIGMA0_RAD = 0.001  # an uncalibrated offset: steering bias 0.5 deg / ratio, gyro bias 0.002 rad/s x L / v
LAT_OFFSET_FLOOR_RAD = 0.0003  # what its calibration leaves: the gyro bias's L b_r / v at another speed (11 vs 20 m/s)
LAT_SLOPE_SIGMA0 = 0.3  # the tires' cornering stiffness against the profile's: worn, winter, inflation (+-30 %)
# ... and each axle's against the other's, apart from that common factor: front and rear tires wear unequally (the
# driven axle faster) and may differ in make, size or pressure (1 sigma, about +-20 %)
LAT_AXLE_SIGMA = 0.12
# ... and a segment's start at least this, in both axles alike: it starts on a road the last one did not show, and a
# surface has its own cornering slope as it has its own slip slope (Burckhardt's table: cobblestone 0.28-0.44 of dry
# asphalt's, snow and ice 0.5-0.6), while calm driving fixes the two axles' difference, not their common factor (in a
# steady turn both axles' forces grow with a_y alike). Chosen on the validation split's calibrated car against 0.3
# (about what calm driving leaves: scores moved by 0.004 at most) and 0.7 (dry roads covered a little more, ice read
# a little less)
LAT_SURFACE_SIGMA = 0.5
# The kinematic angle L r / v against the car's: the profile's wheelbase (a catalogue's, +-1 %), its steering ratio
# (a variable-ratio rack's differs from the nominal by 5-10 % off centre) and the speed (the rolling radius: wear and
# pressure, +-2 %), each a scale on the whole angle
LAT_KINEMATIC_SIGMA = 0.05
# The lateral state of a new car, as `lateral_likelihood` reads it (means, then the covariance's upper triangle): the
# tires' compliances over the profile's (k_f, k_r) 1 each, the common spread on both and each axle's own on its
# diagonal; the kinematic angle's scale error 0, independent of them
COMPLIANCE_PRIOR = np.array(
    [
        1.0,
        1.0,
        0.0,
        LAT_SLOPE_SIGMA0**2 + LAT_AXLE_SIGMA**2,
        LAT_SLOPE_SIGMA0**2,
        0.0,
        LAT_SLOPE_SIGMA0**2 + LAT_AXLE_SIGMA**2,
        0.0,
        LAT_KINEMATIC_SIGMA**2,
    ]
)
LAT_BIAS_SIGMA0_MPS2 = 0.25  # an uncalibrated lateral bias: mounting roll (+-2 deg: 0.34) and the sensor's (+-0.2)
LAT_BIAS_SETTLE_S = 5.0  # the straight-driving mean of a_y - v r settles in seconds (0.1 noise, 50 samples)
LAT_BIAS_FLOOR_MPS2 = 0.1  # what calibration leaves: crossfall varying by 1 % around the one it learned
LAT_CALM_AY_MPS2 = 2.0  # calibration only in calm driving ...
LAT_CALM_SHARE = 0.25  # ... below a quarter of the proven friction: the brush slip angle within 10 % of f / c there
LAT_REF_AGREE = 0.2  # ... with the yaw rate within 20 % (+ 0.02 rad/s) of the steer's reference (not sliding) ...
LAT_SLOPE_MIN_AY_MPS2 = 0.3  # the slope from |v r| above 7 x the gyro's noise times v (errors in the regressor <2 %)
LAT_STEADY_YAW_ACCEL = 0.05  # ... in a steady turn: I_z r' / (m g l) under 0.005 per load (the line is K_us a_y)
LAT_SLOPE_RANGE = (0.5, 2.0)  # the tires' cornering compliance against the profile's: new summer to worn winter tires
INCONSISTENT = 1e-3
# The interval's lower end also reaches every mu the evidence itself does not exclude (Wilks's 90 % likelihood-ratio
# interval: the evidence's ratio posterior / prior within exp(-chi2_1(0.90) / 2) of its largest). The prior is a
# statement about roads in general (most are dry), so its low tail, which the posterior keeps where the evidence is
# silent, excludes the car that is on ice (the prior's 5 % quantile is 0.19): per road, its interval does not cover.
LR_INTERVAL_RATIO = exp(-0.5 * 2.705543)
EXCITED_WIDTH = 0.25
MAX_STEP_S = 0.5

SAMPLE_COLUMNS = (
    "timestamp_ms",
    "wheel_speed_fl_radps",
    "wheel_speed_fr_radps",
    "wheel_speed_rl_radps",
    "wheel_speed_rr_radps",
    "steering_wheel_angle_rad",
    "accel_lon_mps2",
    "accel_lat_mps2",
    "yaw_rate_radps",
    "abs_active",
    "tcs_active",
    "esc_active",
    # the optional channels (CONTRACTS 3.1; slip_slope.py reads the first four, aligning.py the torques): absent or
    # null is NaN, not sent
    "gnss_speed_mps",
    "gnss_speed_accuracy_mps",
    "drive_force_n",
    "brake_force_n",
    "steering_torque_nm",
    "eps_assist_torque_nm",
)
OPTIONAL_COLUMNS = ("tcs_active", "esc_active")  # absent: not reported, taken as not acting
CHANNEL_COLUMNS = SAMPLE_COLUMNS[12:]
S_T, S_W0, S_SWA, S_AX, S_AY, S_R, S_ABS, S_TCS, S_ESC = 0, 1, 5, 6, 7, 8, 9, 10, 11
S_GNSS, S_GNSS_ACC, S_DRIVE, S_BRAKE, S_STEER_T, S_EPS_T = 12, 13, 14, 15, 16, 17
N_BASE = 12  # the columns a sample must have finite
N_S = len(SAMPLE_COLUMNS)

# Parameter vector
(
    Q_M,
    Q_DRAG,
    Q_ROLL,
    Q_LF,
    Q_LR,
    Q_H,
    Q_RADIUS,
    Q_DRIVE,
    Q_C0,
    Q_FRR,
    Q_STEER_RATIO,
    Q_BRAKE_FRONT,
    Q_TRACK_F,
    Q_TRACK_R,
    Q_CA_REAR,
    Q_CA_FRONT,
    Q_IZ,
    Q_C0_FRONT,
    Q_C0_REAR,
    Q_FRONT_DRIVE,
    Q_TRAIL_T0,
    Q_TRAIL_MECH,
) = range(22)
N_Q = 22
DRIVE_CODES = {"fwd": 0.0, "rwd": 1.0, "awd": 2.0}

# Memory: the grid, then calibration and bookkeeping
G0 = 0
K_T = NM * NC
(
    K_STARTED,
    K_BIAS,
    K_BIAS_W,
    K_LR_F,
    K_LR_R,
    K_LR_W,
    K_S0,
    K_SLOPE,
    K_P00,
    K_P01,
    K_P11,
    K_RLS_W,
    K_V_PREV,
    K_REJECTED,
    K_RESTARTS,
    K_INCONSISTENT,
    K_U,
    K_LIMIT,
    K_V_REF,
    K_U_SEEN,
    K_U_LIMIT,
    K_R_PREV,
    K_D_PREV,
    K_BIAS_Y,
    K_BIAS_Y_W,
    K_LAT_B,
    K_LAT_S,
    K_LP00,
    K_LP01,
    K_LP11,
    K_LAT_W,
    K_MU_LO,
) = range(K_T + 1, K_T + 33)
# the optional channels' block (slip_slope.py), appended in issue 26: a state saved before it (N_MEM_V1 numbers) is
# read with the block at its start (state_from_dict)
K_CH = K_T + 33
N_MEM_V1 = K_CH
# the steering torques' block (aligning.py), appended after it: a state saved before (N_MEM_V2 numbers) loads with the
# block fresh
K_AL = K_CH + ch.N_CHANNEL_MEM
N_MEM_V2 = K_AL
# the slip line's input filter (`_calibrate`), appended after it: a state saved before (N_MEM_V3 numbers) loads with
# the filter empty
N_MEM_V3 = K_AL + al.memory_size(NM)
K_LINE_F, K_LINE_S, K_LINE_AGE = N_MEM_V3, N_MEM_V3 + 1, N_MEM_V3 + 2
# a line's slots lie in the order `_line_update` (K_S0 .. K_RLS_W, K_BL_B .. K_BL_W) and `_line_input` (K_LINE_F ..
# K_LINE_AGE, K_BL_X .. K_BL_AGE) read them
# the braking term's calibration (an AWD's front/rear radius ratio, `_calibrate`; the braking line, `_line_update`),
# appended after it: a state saved before (N_MEM_V4 numbers) loads with both unlearned
N_MEM_V4 = N_MEM_V3 + 3
(K_FR, K_FR_W, K_BL_B, K_BL_K, K_BL_P00, K_BL_P01, K_BL_P11, K_BL_W, K_BL_X, K_BL_D, K_BL_AGE) = range(
    N_MEM_V4, N_MEM_V4 + 11
)
N_MEM_V5 = N_MEM_V4 + 11
# the GNSS reference filter's accelerometer error (slip_slope.py), appended after it: a state saved before (N_MEM_V5
# numbers) loads with none known
K_GB = N_MEM_V5
N_MEM_V6 = K_GB + ch.N_BIAS_MEM
# the lateral state (`_lateral`, lateral.py: the tires' cornering compliances over the profile's and the kinematic
# angle's scale error, a Gaussian of N_COMPLIANCE numbers), appended after it: a state saved before (N_MEM_V6 numbers)
# loads with it at a new car's, and so does one saved with the compliances alone (N_MEM_V7: their 5 numbers dropped)
K_KC = N_MEM_V6
N_MEM_V7 = K_KC + 5
N_MEM = K_KC + N_COMPLIANCE
CALIBRATION = {
    "accel_bias_mps2": K_BIAS,
    "accel_bias_weight_s": K_BIAS_W,
    "radius_ratio_left_right_front": K_LR_F,
    "radius_ratio_left_right_rear": K_LR_R,
    "radius_ratio_weight_s": K_LR_W,
    "slip_offset_front_rear": K_S0,
    "slip_slope": K_SLOPE,
    "slip_line_weight_s": K_RLS_W,
    "radius_ratio_front_rear_awd": K_FR,
    "radius_ratio_front_rear_awd_weight_s": K_FR_W,
    "braking_slip_offset": K_BL_B,
    "braking_slip_slope": K_BL_K,
    "braking_line_weight_s": K_BL_W,
    "accel_lat_bias_mps2": K_BIAS_Y,
    "accel_lat_bias_weight_s": K_BIAS_Y_W,
    "understeer_offset_rad": K_LAT_B,
    "cornering_compliance_factor": K_LAT_S,
    "understeer_line_weight_s": K_LAT_W,
}
O_MU, O_LOWER, O_UPPER, O_EXCITED, O_VALID = range(5)
N_OUT = 5


def pack(vehicle: VehicleParams) -> np.ndarray:
    """The profile as the kernel's parameter vector (Q_*)."""
    if not isinstance(vehicle, VehicleParams):
        raise TypeError(f"vehicle must be a VehicleParams, got {type(vehicle).__name__}")
    q = np.zeros(N_Q)
    q[Q_M] = vehicle.mass_kg
    q[Q_DRAG] = drag_per_mass(vehicle)
    q[Q_ROLL] = roll_per_lateral_accel(vehicle)
    q[Q_LF], q[Q_LR], q[Q_H] = vehicle.cg_to_front_axle_m, vehicle.cg_to_rear_axle_m, vehicle.cg_height_m
    q[Q_RADIUS] = vehicle.wheel_radius_m
    q[Q_DRIVE] = DRIVE_CODES[vehicle.drive]
    driven = vehicle.tire_rear if vehicle.drive == "rwd" else vehicle.tire_front
    q[Q_C0] = driven.longitudinal_stiffness_per_load
    q[Q_FRR] = vehicle.rolling_resistance
    q[Q_STEER_RATIO] = vehicle.steering_ratio
    q[Q_BRAKE_FRONT] = vehicle.brake_front_share
    q[Q_TRACK_F], q[Q_TRACK_R] = vehicle.track_front_m, vehicle.track_rear_m
    q[Q_CA_REAR] = vehicle.tire_rear.cornering_stiffness_per_load_per_rad
    q[Q_CA_FRONT] = vehicle.tire_front.cornering_stiffness_per_load_per_rad
    q[Q_IZ] = vehicle.yaw_inertia_kgm2
    q[Q_C0_FRONT] = vehicle.tire_front.longitudinal_stiffness_per_load
    q[Q_C0_REAR] = vehicle.tire_rear.longitudinal_stiffness_per_load
    q[Q_FRONT_DRIVE] = vehicle.drive_split[0]
    q[Q_TRAIL_T0] = vehicle.tire_front.pneumatic_trail_m
    q[Q_TRAIL_MECH] = vehicle.mechanical_trail_m
    return q


@njit(cache=True)
def _c_marginal(mem):
    """The grid's stiffness marginal: its mass at each of C_FACTORS, summed over mu."""
    return mem[G0 : G0 + NM * NC].reshape((NM, NC)).sum(axis=0)


@njit(cache=True)
def _mu_marginal(mem):
    """The grid's mu marginal: its mass at each of MU_GRID, summed over the stiffness."""
    return mem[G0 : G0 + NM * NC].reshape((NM, NC)).sum(axis=1)


@njit(cache=True)
def _compliance_collapse(post, weights, out):
    """One Gaussian (N_COMPLIANCE numbers, as COMPLIANCE_PRIOR's) with the moments of the grid mus' Gaussians `post`
    (N_COMPLIANCE numbers a mu), weighted by `weights` (one a grid mu)."""
    d = N_LATERAL_PARAMS
    total = 0.0
    mean = np.zeros(d)
    second = np.zeros((d, d))
    m_i = np.empty(d)
    c_i = np.empty((d, d))
    for i in range(NM):
        w = weights[i]
        total += w
        unpack_gaussian(post[i * N_COMPLIANCE : (i + 1) * N_COMPLIANCE], m_i, c_i)
        for a in range(d):
            mean[a] += w * m_i[a]
            for b in range(d):
                second[a, b] += w * (c_i[a, b] + m_i[a] * m_i[b])
    mean /= total
    for a in range(d):
        for b in range(d):
            second[a, b] = second[a, b] / total - mean[a] * mean[b]
    pack_gaussian(mean, second, out)


@njit(cache=True)
def _lateral_surface_unknown(comp):
    """The lateral state's compliances with their common factor as unknown as a new road leaves it: a surface scales
    both axles' cornering stiffness alike (k_f, k_r to s k_f, s k_r), so the covariance along (k_f, k_r, 0) is raised
    to LAT_SURFACE_SIGMA of the means where it is narrower. The means, the axles' difference and the kinematic scale
    are kept."""
    d = N_LATERAL_PARAMS
    mean = np.empty(d)
    cov = np.empty((d, d))
    unpack_gaussian(comp, mean, cov)
    norm2 = mean[0] * mean[0] + mean[1] * mean[1]
    if not norm2 > 0.0:
        return
    along = 0.0
    for a in range(2):
        for b in range(2):
            along += mean[a] * cov[a, b] * mean[b]
    add = LAT_SURFACE_SIGMA**2 - along / (norm2 * norm2)  # the common factor's variance short of the spread
    if add > 0.0:
        for a in range(2):
            for b in range(2):
                cov[a, b] += add * mean[a] * mean[b]
        pack_gaussian(mean, cov, comp)


@njit(cache=True)
def _start(mem, keep_stiffness):
    """The grid at a segment's start: the prior over mu, times the stiffness marginal (kept across gaps, as is the
    lateral state: a restart leaves the tires as they were, but the road is new, and with it the surface's share of the
    tires' cornering compliance: `_lateral_surface_unknown`), or a new car's (`init_memory`, whose appended blocks hold
    a new car's lateral state)."""
    cm = _c_marginal(mem) if keep_stiffness else C_PRIOR.copy()
    if keep_stiffness:
        _lateral_surface_unknown(mem[K_KC : K_KC + N_COMPLIANCE])
    total = 0.0
    for j in range(NC):
        total += cm[j]
    for i in range(NM):
        for j in range(NC):
            mem[G0 + i * NC + j] = PRIOR[i] * cm[j] / total
    mem[K_STARTED] = 1.0
    # a restart may follow a new power-on, and a MEMS gyro's bias comes back different at each (its turn-on
    # repeatability is as large as its bias; the simulator's sensors draw theirs per run): the understeer line's offset
    # b, which carries L b_r / v, is as unknown as an uncalibrated car's, and no longer correlated with the slope (the
    # tires', which a power-on leaves as they were)
    mem[K_LP00] = LAT_OFFSET_SIGMA0_RAD**2
    mem[K_LP01] = 0.0
    mem[K_V_PREV] = -1.0
    mem[K_V_REF] = 0.0
    ch.unlock(mem, K_CH)  # the GNSS reference's speed is the last segment's: lock afresh on this one's fixes
    mem[K_U_SEEN] = 0.0
    mem[K_U_LIMIT] = 0.0
    mem[K_MU_LO] = _quantile(PRIOR, 0.05)


@njit(cache=True)
def _stiffness_prior(mem, q, out):
    """What the grid's stiffness forgets towards: the broad prior, narrowed around the calibrated slip line's 1 / slope
    (the low-force stiffness, Gustafsson's slip slope) once it has STIFFNESS_CALIBRATED_S of data behind it."""
    calibrated = mem[K_RLS_W] >= STIFFNESS_CALIBRATED_S and mem[K_SLOPE] > 0.0
    centre, spread = 0.0, 1.0
    if calibrated:
        centre = -np.log(mem[K_SLOPE] * q[Q_C0])  # log of the calibrated stiffness factor
        spread = sqrt(mem[K_P11] / mem[K_SLOPE] ** 2 + STIFFNESS_SURFACE_SPREAD**2)
    total = 0.0
    for j in range(NC):
        out[j] = C_PRIOR[j]
        if calibrated:
            out[j] *= exp(-0.5 * ((np.log(C_FACTORS[j]) - centre) / spread) ** 2)
        total += out[j]
    for j in range(NC):
        out[j] /= total


@njit(cache=True)
def _moving(v):
    """The share of FORGET_PER_S and of the walk's variance at speed v: 1 from FORGET_MOVING_MPS, in proportion below."""
    return min(v / FORGET_MOVING_MPS, 1.0)


@njit(cache=True)
def _forget_rate(v):
    """How fast the grid forgets (1/s) at speed v: FORGET_PER_S while the car moves, in proportion to the speed below
    FORGET_MOVING_MPS, and the road's own change in place (FORGET_STILL_PER_S)."""
    return FORGET_PER_S * _moving(v) + FORGET_STILL_PER_S


@njit(cache=True)
def _predict(mem, dt, v, c_prior):
    """Mu diffuses (random walk on the grid, its moves accepted against the prior: WALK_UP, WALK_DOWN) and the grid is
    mixed with the prior; stiffness forgets slowly towards its (calibrated) prior. All three while the car moves
    (`_moving`): the stiffness is the tire's on this surface, which a standing car does not leave.

    The mixing redraws mu and keeps the tire: its stiffness from the grid's marginal, except while the last sample was
    at the limit (K_U_LIMIT set). There the evidence pairs mu with the stiffness (a low road, or a soft tire far below
    its peak) and says nothing of the tire alone, and the marginal follows the pairing: redrawn from it, sample after
    sample, the mass moved to the one pairing that needs no road to stay the same, a very soft tire on any road, and the
    median back to the prior's while traction control held for 10 s on ice. At the limit the redraw takes the
    stiffness from c_prior, what calibration knows of the tire (docs/ESTIMATORS.md 14)."""
    step = MU_GRID[1] - MU_GRID[0]
    var = (MU_WALK_PER_SQRT_S * MU_WALK_PER_SQRT_S * _moving(v) * dt) / (step * step)  # in grid steps^2
    side = min(0.5 * var, 0.25)  # a 3-tap kernel with this variance (up to its limit; the forgetting does the rest)
    forget = 1.0 - exp(-_forget_rate(v) * dt)
    forget_c = 1.0 - exp(-C_FORGET_PER_S * _moving(v) * dt)
    cm = c_prior if mem[K_U_LIMIT] > 0.0 else _c_marginal(mem)
    for j in range(NC):
        col = np.empty(NM)
        for i in range(NM):
            col[i] = mem[G0 + i * NC + j]
        for i in range(NM):
            p = col[i] * (1.0 - side * (WALK_UP[i] + WALK_DOWN[i]))
            if i > 0:
                p += side * WALK_UP[i - 1] * col[i - 1]
            if i < NM - 1:
                p += side * WALK_DOWN[i + 1] * col[i + 1]
            c_target = (1.0 - forget_c) * cm[j] + forget_c * c_prior[j]
            mem[G0 + i * NC + j] = (1.0 - forget) * (
                (1.0 - forget_c) * p + forget_c * PRIOR[i] * c_prior[j]
            ) + forget * PRIOR[i] * c_target


@njit(cache=True)
def _compliance_forget(mem, dt):
    """The lateral state (compliances, kinematic scale) forgets towards a new car's at C_FORGET_PER_S, as the grid's
    stiffness does: an Ornstein-Uhlenbeck step, x0 + e^(-a) (x - x0) for the means and the covariance towards the
    prior's (its stationary law)."""
    keep = exp(-C_FORGET_PER_S * dt)
    for k in range(N_COMPLIANCE):
        w = keep if k < N_LATERAL_PARAMS else keep * keep
        mem[K_KC + k] = COMPLIANCE_PRIOR[k] + w * (mem[K_KC + k] - COMPLIANCE_PRIOR[k])


@njit(cache=True)
def _apply(mem, like, temper, inconsistent=INCONSISTENT):
    """Multiply the grid by a likelihood (NM x NC) raised to `temper`; skip it (False) if no cell explains the data
    (the grid's total likelihood under `inconsistent` of the best cell's)."""
    best = 0.0
    total = 0.0
    for i in range(NM):
        for j in range(NC):
            best = max(best, like[i, j])
            total += mem[G0 + i * NC + j] * like[i, j]
    if not best > 0.0 or total < inconsistent * best:
        mem[K_INCONSISTENT] += 1.0
        return False
    norm = 0.0
    for i in range(NM):
        for j in range(NC):
            ratio = like[i, j] / best
            v = mem[G0 + i * NC + j] * (ratio if temper == 1.0 else ratio**temper)
            mem[G0 + i * NC + j] = v
            norm += v
    for k in range(NM * NC):
        mem[G0 + k] /= norm
    return True


@njit(cache=True)
def _apply_at_stiffness(mem, like, inconsistent):
    """`_apply` (already tempered) for a term that speaks of mu through the tire's slip curve: skipped when no mu
    explains it at the stiffness the grid holds (its C marginal), rather than when the grid's cells as they are do not.
    The road's mu jumps at a patch's edge, the tire's stiffness does not (C_FORGET_PER_S): judged against the posterior
    of the road behind, the slip of the first metres on ice is a surprise, not an inconsistency."""
    best = 0.0
    for i in range(NM):
        for j in range(NC):
            best = max(best, like[i, j])
    pc = _c_marginal(mem)
    explained = 0.0
    for i in range(NM):
        e = 0.0
        for j in range(NC):
            e += pc[j] * like[i, j]
        explained = max(explained, e)
    if not best > 0.0 or explained < inconsistent * best * pc.sum():
        mem[K_INCONSISTENT] += 1.0
        return False
    return _apply(mem, like, 1.0, 0.0)


@njit(cache=True)
def _demand_likelihood(mu, u, s_u):
    """p(u | mu) up to a factor: the driver's demand d has density exp(-d / DEMAND_G) / DEMAND_G whatever the road;
    the tires transmit u = d where d < mu, and where d >= mu (probability exp(-mu / DEMAND_G)) they saturate, u / mu
    then uniform in [ETA_LIMIT, 1]. Divided by exp(-u / DEMAND_G) / DEMAND_G:
    P(mu >= u) (1 + DEMAND_G exp(-(mu - u) / DEMAND_G) [u / mu in the band] / band)."""
    s_lim = sqrt(s_u * s_u + (0.05 * mu) ** 2)
    band = (1.0 - ETA_LIMIT) * mu
    saturated = DEMAND_G * exp(-max(mu - u, 0.0) / DEMAND_G) / band
    return normal_cdf((mu - u) / s_u) * (1.0 + saturated * normal_cdf((u - ETA_LIMIT * mu) / s_lim))


@njit(cache=True)
def _bound_likelihood(u, u_seen, s_u, like):
    """What a new largest utilisation u adds to the one u_seen already applied."""
    for i in range(NM):
        lk = _demand_likelihood(MU_GRID[i], u, s_u) / max(_demand_likelihood(MU_GRID[i], u_seen, s_u), 1e-300)
        for j in range(NC):
            like[i, j] = lk


@njit(cache=True)
def _band(mu, u_axle, s_u, eta):
    """Whether u_axle lies in [eta mu, mu], blurred by the measurement's noise. A statement of membership, not a
    density: a controller stays on for many samples that say the same, and a density's 1 / ((1 - eta) mu), applied
    again at each, would push mu down to the band's lower end for no new reason."""
    s_lim = sqrt(s_u * s_u + (0.05 * mu) ** 2)
    return normal_cdf((mu - u_axle) / s_u) * normal_cdf((u_axle - eta * mu) / s_lim)


@njit(cache=True)
def _brush_force(slip, mu, c):
    """The brush model's force per load at a slip (magnitude): mu (1 - (1 - z)^3), z = C s / (3 mu), mu beyond z = 1."""
    z = min(c * slip / (3.0 * mu), 1.0)
    return mu * (1.0 - (1.0 - z) ** 3)


@njit(cache=True)
def _soft_between(p, lo, s_lo, hi, s_hi):
    """P(lo <= p <= hi) with each end blurred (normal, s_lo and s_hi): Phi((p - lo) / s_lo) Phi((hi - p) / s_hi), each
    factor taken as 0 or 1 beyond 6 sigma (1e-9 off), where it costs no erf."""
    a = (p - lo) / s_lo
    b = (hi - p) / s_hi
    if a < -6.0 or b < -6.0:
        return 0.0
    return (1.0 if a > 6.0 else normal_cdf(a)) * (1.0 if b > 6.0 else normal_cdf(b))


@njit(cache=True)
def _abs_likelihood(u_car, s_car, u_first, s_first, c0, like):
    """ABS acting. With a fixed brake distribution the axle it names first (u_first: its utilisation by the profile's
    brake_front_share) reaches its limit first; ABS then holds that axle there and its force no longer follows the
    pedal, while the other axle's does, up to its own limit. The pedal is not sent, so every state between "only the
    first axle at its limit" (its held force per load p = u_first) and "both at their limit" (p = u_car, the car's
    utilisation) is possible: u_car <= p <= u_first, each end blurred by its own noise (s_car, s_first). What ABS holds
    is a slip band (ABS_SLIP_BAND): p is the brush force there, the peak mu for a stiff tire and below it for a soft
    one (cobblestone, snow, worn: C small). The likelihood of (mu, C) is the share of that band's forces (uniform over
    the band's slips) that lies in [u_car, u_first]: flat over mu in between for a stiff tire, and a soft tire's wider
    band pays for the forces that fall outside."""
    step = (ABS_SLIP_BAND[1] - ABS_SLIP_BAND[0]) / ABS_BAND_POINTS
    for i in range(NM):
        mu = MU_GRID[i]
        s_mu = 0.03 * mu  # the brush model's force against the tires' at the band
        s_lo = sqrt(s_car * s_car + s_mu * s_mu)
        s_hi = sqrt(s_first * s_first + s_mu * s_mu)
        for j in range(NC):
            c = c0 * C_FACTORS[j]
            total = 0.0
            for k in range(ABS_BAND_POINTS):
                slip = ABS_SLIP_BAND[0] + (k + 0.5) * step
                if c * slip >= 3.0 * mu:  # saturated here, so at every larger slip of the band: force mu
                    total += (ABS_BAND_POINTS - k) * _soft_between(mu, u_car, s_lo, u_first, s_hi)
                    break
                total += _soft_between(_brush_force(slip, mu, c), u_car, s_lo, u_first, s_hi)
            like[i, j] = total / ABS_BAND_POINTS


@njit(cache=True)
def _axle_force_sd(f, a, s_u, psi):
    """The noise of one axle's force per load f, read from the accelerometer's |a_x| = a (s_u its noise per g) through
    the axle's load share psi: a_x's (f g / a), and the load share's, known to LOAD_SHARE_SPREAD (f = F / (psi W)
    moves by LOAD_SHARE_SPREAD / psi of itself). ABS's first axle and traction control's driven one."""
    return sqrt((s_u * f * G_MPS2 / a) ** 2 + (f * LOAD_SHARE_SPREAD / psi) ** 2)


@njit(cache=True)
def _tcs_likelihood(u_axle, s_u, c0, like):
    """Traction control acting: the driven wheels crossed its slip threshold, so the driven axle's force per load u_axle
    (the largest of the flag's last LIMIT_PEAK_S) is the tire's at some slip in TCS_SLIP_BAND, which is not sent: the
    likelihood of (mu, C) is the best over that slip, 1 where u_axle lies between the brush forces at the band's ends
    and falling as a normal beyond (u_axle's noise s_u, `_axle_force_sd`, and the brush model's 3 % of mu). A stiff
    tire's band lies at or near its peak, which puts mu within a few times u_axle; a soft one (cobblestone, winter
    tires: C small) reaches the band far below its peak and leaves mu open above. A membership, as _band: the flag
    stays on for many samples that say the same, and a density over the band's width would favour, at every one of
    them, the narrowest band that holds u_axle: a saturated tire, the lowest mu."""
    for i in range(NM):
        mu = MU_GRID[i]
        s_f = sqrt(s_u * s_u + (0.03 * mu) ** 2)
        for j in range(NC):
            c = c0 * C_FACTORS[j]
            lo = _brush_force(TCS_SLIP_BAND[0], mu, c)
            hi = _brush_force(TCS_SLIP_BAND[1], mu, c)
            miss = max(lo - u_axle, u_axle - hi, 0.0) / s_f
            like[i, j] = exp(-0.5 * miss * miss)


@njit(cache=True)
def _limit_likelihood(u_axle, s_u, kind, like):
    """At (or near) the friction limit without ABS or traction control (LIMIT_*): ESC's engine cut and a locked or
    spinning wheel, u_axle / mu spread over [eta, 1]."""
    for i in range(NM):
        mu = MU_GRID[i]
        if kind == LIMIT_ESC:
            lk = _band(mu, u_axle, s_u, ETA_ESC)
        else:
            lk = _band(mu, u_axle, s_u, ETA_LOCK) / ((1.0 - ETA_LOCK) * mu)
        for j in range(NC):
            like[i, j] = lk


@njit(cache=True)
def _slip_likelihood(f, s, v, c0, like):
    """The brush model's slip at force per load f against the measured slip s, for each (mu, C), already raised to
    TEMPER (one exp a cell instead of an exp and a power: this runs at every straight driving sample)."""
    s_floor = SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v
    for i in range(NM):
        shape = brush_slip(f, MU_GRID[i], c0)  # the slip at C = c0; at C it is shape / C
        for j in range(NC):
            pred = shape / C_FACTORS[j]
            sig = s_floor + SLIP_MODEL_SHARE * abs(pred)
            like[i, j] = exp(-0.5 * TEMPER * ((s - pred) / sig) ** 2)


@njit(cache=True)
def _quantile(pm, level):
    """The level-quantile of the mu marginal, the grid's cells read as bins of width `step` around each value."""
    step = MU_GRID[1] - MU_GRID[0]
    acc = 0.0
    for i in range(NM):
        if acc + pm[i] >= level:
            frac = (level - acc) / pm[i] if pm[i] > 0.0 else 0.5
            return MU_GRID[i] - 0.5 * step + frac * step
        acc += pm[i]
    return MU_GRID[NM - 1] + 0.5 * step


def mu_quantile(pm, level: float) -> float:
    """The level-quantile of a mu marginal over MU_GRID, read as pmf reads its own intervals (the prior baseline of
    evaluation/baseline.py reads the prior through this: one rule)."""
    if not 0.0 < level < 1.0:
        raise ValueError(f"mu_quantile: level must lie in (0, 1), got {level!r}")
    pm = np.asarray(pm, dtype=np.float64)
    if pm.shape != (NM,) or not (pm >= 0.0).all() or abs(pm.sum() - 1.0) > 1e-9:
        raise ValueError(f"mu_quantile: pm must be {NM} non-negative weights summing to 1 over MU_GRID")
    return float(_quantile(pm, level))


@njit(cache=True)
def wheel_kinematics(q, yaw_rate, delta, ay, gain, offset):
    """The speed over ground along its heading at which each wheel (fl, fr, rl, rr) rolls without slip, as
    gain_i * v + offset_i of the CoG's longitudinal speed v, for a rigid body turning at `yaw_rate` with the front
    wheels steered by `delta` (ISO 8855: both positive left; the left wheels at +track / 2).

    Hub velocity in the body frame: (v - r y_i, v_y + r x_i). The CoG's lateral speed v_y is the rear axle's
    kinematics with the rear tires' slip angle: v_y = r b - v alpha_r, alpha_r = a_y / (g C_alpha_r) (the rear axle
    carries m a_y a / L of lateral force on m g a / L of load, whatever the load transfer). The rear wheels roll along
    the body's x axis: v - r y_i. The front wheels along their heading, the common delta (cos, sin projection):
    (v - r y_i) cos delta + (r L - v alpha_r) sin delta. Not Ackermann's own angle for each: the projection's
    error is second order in the heading's error (the hub speed times 1 - cos), at R = 10 m 1.3 degrees and 3e-4 of
    the speed, below the slip noise, and a car's real steering geometry lies between parallel and Ackermann."""
    lf, lr = q[Q_LF], q[Q_LR]
    half_f, half_r = 0.5 * q[Q_TRACK_F], 0.5 * q[Q_TRACK_R]
    alpha_r = ay / (G_MPS2 * q[Q_CA_REAR])
    c, s = cos(delta), sin(delta)
    gain[0] = gain[1] = max(c - alpha_r * s, 0.1)  # 0.1: a steer of 84 degrees, beyond any road wheel's
    offset[0] = yaw_rate * ((lf + lr) * s - half_f * c)
    offset[1] = yaw_rate * ((lf + lr) * s + half_f * c)
    gain[2] = gain[3] = 1.0
    offset[2] = -yaw_rate * half_r
    offset[3] = yaw_rate * half_r


@njit(cache=True)
def _repeats(dt, v):
    """How many times the grid counts one sample's evidence within its memory (tempered samples dt apart, forgotten at
    `_forget_rate(v)`): 10 at 10 Hz while the car moves, more where it creeps. A systematic error (the same at every
    sample) whose variance is multiplied by this counts once. A sample without a step (dt = 0) counts once."""
    return TEMPER / (1.0 - exp(-_forget_rate(v) * dt)) if dt > 0.0 else 1.0


@njit(cache=True)
def _brake_slip_likelihood(
    d,
    x,
    f_front,
    f_rear,
    f_front_static,
    f_rear_static,
    share,
    psi,
    s_f,
    v,
    c0_front,
    c0_rear,
    line,
    line_var,
    repeats,
    like,
):
    """Braking without a controller: the front axle's slip minus the rear's, d, against the brush model's at each
    axle's force per load (f_front, f_rear: the profile's brake split over its axle loads, their sum per weight x),
    already raised to TEMPER. Linear in the force, d is (f_front / c_f - f_rear / c_r) whatever mu; the axle nearer its
    limit slipping faster than that tells mu. Where the car's braking line is calibrated (`line` its value b + k_b x at
    this x, line_var its variance, not NaN) the linear part at the static loads is the line's (f_front_static,
    f_rear_static: the same forces over the static loads), and the brush model gives the rest: its slips at the loads
    the braking transfers, less the static line's; before, everything comes from the catalogue and the grid's
    stiffness. The spread: the wheels' noise (as `_slip_likelihood`), the brush model's error
    on each axle's slip, the forces' relative noise s_f, and what the car's split (BRAKE_SHARE_SPREAD: it moves the
    front force per load by f_front / share of itself and the rear's the other way) and front load share psi
    (LOAD_SHARE_SPREAD) leave unknown: of the whole slip before the line is calibrated, of its excess after, beside the
    line's own variance. Those are the car's, the same at every sample: their variance is multiplied by
    `repeats`, the number of times the grid counts a sample's evidence, so that they count once."""
    s_floor = SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v
    calibrated = np.isfinite(line_var)
    for i in range(NM):
        mu = MU_GRID[i]
        brush_f = brush_slip(f_front, mu, c0_front)  # each at C = the profile's; at C factor k it is this / k
        brush_r = brush_slip(f_rear, mu, c0_rear)
        slip_f, slip_r = brush_f, brush_r
        g_f = brush_slip_angle_slope(f_front, mu, c0_front)  # d slip / d f
        g_r = brush_slip_angle_slope(f_rear, mu, c0_rear)
        if calibrated:  # what the static line does not hold: the load transfer and the curve's excess
            slip_f -= f_front_static / c0_front
            slip_r -= f_rear_static / c0_rear
            g_f -= 1.0 / c0_front
            g_r -= 1.0 / c0_rear
        k_f, k_r = g_f * f_front, g_r * f_rear
        spread = sqrt(
            repeats * ((k_f / share + k_r / (1.0 - share)) * BRAKE_SHARE_SPREAD) ** 2
            + repeats * ((k_f / psi + k_r / (1.0 - psi)) * LOAD_SHARE_SPREAD) ** 2
            + ((k_f - k_r) * s_f) ** 2
            + (SLIP_MODEL_SHARE * (brush_f + brush_r)) ** 2
        )
        for j in range(NC):
            pred = (slip_f - slip_r) / C_FACTORS[j]
            sig2 = s_floor * s_floor + (spread / C_FACTORS[j]) ** 2
            if calibrated:
                pred += line
                sig2 += repeats * line_var
            like[i, j] = exp(-0.5 * TEMPER * (d - pred) ** 2 / sig2)


@njit(cache=True)
def _line_input(mem, k, x, y, dt, age):
    """A line's regressor and response through their first-order filter over SLIP_LINE_FILTER_S (mem[k], mem[k + 1];
    mem[k + 2] the seconds it has run without a break): on from where it was if it fed the line at the previous sample
    (`age`, that sample's mem[k + 2], above 0), else started at the raw values. Returns the filtered pair and whether
    the input has run LINE_SETTLE_S (the braking line is fed only then; why: that constant's comment)."""
    if age > 0.0:
        a = 1.0 - exp(-dt / SLIP_LINE_FILTER_S)
        mem[k] += a * (x - mem[k])
        mem[k + 1] += a * (y - mem[k + 1])
    else:
        mem[k], mem[k + 1] = x, y
    mem[k + 2] = age + dt
    return mem[k], mem[k + 1], mem[k + 2] >= LINE_SETTLE_S


@njit(cache=True)
def _line_update(mem, k, x, y, dt, v):
    """One step of a line y = mem[k] + mem[k + 1] x by recursive least squares forgetting over RLS_TAU_S (mem[k + 2:
    k + 5] its covariance P00, P01, P11; mem[k + 5] the seconds it has seen), the wheels' slip noise at v its
    measurement's: K = P h / (h' P h + r), h = (1, x); P = (I - K h') P."""
    lam = exp(-dt / RLS_TAU_S)
    p00, p01, p11 = mem[k + 2] / lam, mem[k + 3] / lam, mem[k + 4] / lam
    ph0, ph1 = p00 + p01 * x, p01 + p11 * x
    den = ph0 + ph1 * x + (SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v) ** 2
    k0, k1 = ph0 / den, ph1 / den
    err = y - (mem[k] + mem[k + 1] * x)
    mem[k] += k0 * err
    mem[k + 1] += k1 * err
    mem[k + 2] = p00 - k0 * ph0
    mem[k + 3] = p01 - k0 * ph1
    mem[k + 4] = p11 - k1 * ph1
    mem[k + 5] += dt


@njit(cache=True)
def _calibrate(mem, q, smp, dt, v_cog, gain, offset, v, ax_c, atx, f_d, s_raw, straight, driving):
    """Update the self-calibration with this sample (after its evidence was used with the previous calibration)."""
    # the slip line's filter goes on only from a sample that fed it (K_LINE_AGE: its age then, set again below if this
    # one does)
    line_age = mem[K_LINE_AGE]
    mem[K_LINE_AGE] = 0.0
    controller = smp[S_ABS] + smp[S_TCS] + smp[S_ESC] > 0.0
    if dt <= 0.0 or controller or v < 3.0:
        return
    # accelerometer bias: a_x - dv/dt over steady driving
    v_prev = mem[K_V_PREV]
    if v_prev >= 0.0 and abs(smp[S_AX]) < 2.5 and abs(smp[S_R]) < 0.1:
        dvdt = (v - v_prev) / dt
        window = max(BIAS_TAU_S, min(mem[K_BIAS_W], BIAS_AVERAGE_S))  # grows with the steady driving seen
        mem[K_BIAS] += dt / window * ((smp[S_AX] - dvdt) - mem[K_BIAS])
        mem[K_BIAS_W] += dt
    if v < SLIP_MIN_SPEED_MPS or not straight or not driving:
        return
    kin = np.empty(4)
    for i in range(4):
        if not v_cog[i] > 0.5 * v:  # a wheel locked or spinning backwards: no ratio to learn
            return
        kin[i] = gain[i] * v + offset[i]  # the speed it rolls at without slip
    # left/right radius ratios (straight driving, each wheel's count against its own kinematic speed: a gentle curve
    # turns the outer wheels faster by track / R, 2.6 % at the 60 m radius that `straight` still admits)
    w = 1.0 - exp(-dt / RADIUS_TAU_S)
    mem[K_LR_F] += w * (smp[S_W0] * kin[1] / (smp[S_W0 + 1] * kin[0]) - 1.0 - mem[K_LR_F])
    mem[K_LR_R] += w * (smp[S_W0 + 2] * kin[3] / (smp[S_W0 + 3] * kin[2]) - 1.0 - mem[K_LR_R])
    mem[K_LR_W] += dt
    # an AWD's front/rear radius ratio (the braking term's zero) in calm driving: its running mean, then RADIUS_TAU_S's
    if q[Q_DRIVE] == 2.0 and abs(atx) < FR_CALM_MPS2:
        w = max(1.0 - exp(-dt / RADIUS_TAU_S), dt / (mem[K_FR_W] + dt))
        mem[K_FR] += w * ((v_cog[0] + v_cog[1]) / (v_cog[2] + v_cog[3]) - 1.0 - mem[K_FR])
        mem[K_FR_W] += dt
    # the slip line s = s0 + slope f at low force, by recursive least squares with forgetting, on the filtered force
    # and slip (SLIP_LINE_FILTER_S), the filter restarted wherever the line's conditions break
    if not abs(f_d) < 0.15:
        return
    f_d, s_raw, _ = _line_input(mem, K_LINE_F, f_d, s_raw, dt, line_age)
    _line_update(mem, K_S0, f_d, s_raw, dt, v)


@njit(cache=True)
def init_brake_line(mem, q):
    """The braking line's start: b = 0 +- BRAKE_ZERO_SIGMA, and the catalogue's k_b (static load share, the profile's
    stiffnesses), known to half the axles' slips per force (the tires' stiffness alone is known to a factor of 1.8,
    C_PRIOR)."""
    share, psi = q[Q_BRAKE_FRONT], q[Q_LR] / (q[Q_LF] + q[Q_LR])
    front, rear = share / psi / q[Q_C0_FRONT], (1.0 - share) / (1.0 - psi) / q[Q_C0_REAR]
    mem[K_BL_B] = 0.0
    mem[K_BL_K] = front - rear
    mem[K_BL_P00] = BRAKE_ZERO_SIGMA**2
    mem[K_BL_P01] = 0.0
    mem[K_BL_P11] = (0.5 * (front + rear)) ** 2
    mem[K_BL_W] = 0.0


@njit(cache=True)
def init_appended_blocks(mem, q):
    """The blocks appended to the memory's layout since its first version, each as a new car's: the optional channels'
    (V1), the steering torques' (V2), the braking line's (V4), the GNSS reference's accelerometer error (V5) and the
    lateral state (V6; its three-parameter layout since V7). A state saved before one of them loads with that block
    from here (`state_from_dict`)."""
    ch.init_channel_memory(mem, K_CH, q[Q_C0_FRONT], q[Q_C0_REAR])
    al.init_aligning_memory(mem, K_AL, NM)
    init_brake_line(mem, q)
    ch.init_bias_memory(mem, K_GB, BIAS_SIGMA0_MPS2)
    mem[K_KC : K_KC + N_COMPLIANCE] = COMPLIANCE_PRIOR


@njit(cache=True)
def init_memory(mem, q):
    mem[:] = 0.0
    mem[K_SLOPE] = 1.0 / q[Q_C0]
    mem[K_P00] = 0.02**2  # radius mismatch: +-2 % a wheel
    mem[K_P11] = (0.5 / q[Q_C0]) ** 2
    mem[K_P01] = 0.0
    mem[K_LAT_S] = 1.0
    mem[K_LP00] = LAT_OFFSET_SIGMA0_RAD**2
    mem[K_LP11] = LAT_SLOPE_SIGMA0**2
    init_appended_blocks(mem, q)
    _start(mem, False)
    mem[K_STARTED] = 0.0


@njit(cache=True)
def _lateral(mem, q, smp, dt, v, aty, atx, fz_front, fz_rear, like, at_limit):
    """The lateral channel: the understeer angle delta - L r / v against the brush model's alpha_f - alpha_r at the
    axles' forces per load (lateral.py), as evidence over mu; then, in calm driving, the calibration of its line
    (offset and slope: the understeer gradient over the profile's) by recursive least squares."""
    if not dt > 0.0 or mem[K_V_PREV] < 0.0 or v < SLIP_MIN_SPEED_MPS or smp[S_ABS] > 0.0:
        return
    delta = smp[S_SWA] / q[Q_STEER_RATIO]
    if abs(delta) > LAT_MAX_STEER_RAD:
        return
    m, lf, lr, iz = q[Q_M], q[Q_LF], q[Q_LR], q[Q_IZ]
    wb = lf + lr
    c_f, c_r = q[Q_CA_FRONT], q[Q_CA_REAR]
    yaw_accel = (smp[S_R] - mem[K_R_PREV]) / dt
    steer_rate = (delta - mem[K_D_PREV]) / dt
    ay = aty - mem[K_BIAS_Y]
    f_f, f_r = axle_lateral_per_load(m, lf, lr, iz, ay, yaw_accel, fz_front, fz_rear)
    kinematic = wb * smp[S_R] / v
    understeer = delta - kinematic - mem[K_LAT_B]
    # the measurement's variance: steering and gyro noise, the groups' time offsets and the tire's lag on a changing
    # steer, the yaw acceleration's noise (a difference of two gyro samples) through the axles' forces
    lag = LAT_TIME_OFFSET_S + LAT_RELAXATION_M / v
    rate = (abs(steer_rate) + wb * abs(yaw_accel) / v) * lag
    s_racc = sqrt(2.0) * LAT_YAW_NOISE_RADPS / dt * iz / (m * G_MPS2) * (1.0 / (lr * c_f) + 1.0 / (lf * c_r))
    var_meas = (
        (LAT_STEER_NOISE_RAD / q[Q_STEER_RATIO]) ** 2
        + (LAT_YAW_NOISE_RADPS * wb / v) ** 2
        + rate * rate
        + (mem[K_LAT_S] * s_racc) ** 2
    )
    # not at a wheel locked or spinning (its axle's forces are not the brush model's; the limit term speaks), nor where
    # the axles brake or drive hard (|a_x| from BRAKE_MIN_MPS2, where the braking and drive terms read them): an axle's
    # side slip then depends on its longitudinal slip too (combined slip), which this term does not know
    if not at_limit and abs(atx) < BRAKE_MIN_MPS2:
        # each axle's longitudinal force per load (braking by the brake share, driving by the driven axle's)
        fx_f = fx_r = atx / G_MPS2  # all-wheel drive: each axle by its load
        if atx < 0.0:
            fx_f = q[Q_BRAKE_FRONT] * m * atx / fz_front
            fx_r = (1.0 - q[Q_BRAKE_FRONT]) * m * atx / fz_rear
        elif q[Q_DRIVE] == 0.0:
            fx_f, fx_r = m * atx / fz_front, 0.0
        elif q[Q_DRIVE] == 1.0:
            fx_f, fx_r = 0.0, m * atx / fz_rear
        # the offset's uncertainty is noise a sample has; the tires' compliances are the state K_KC carries
        var0 = var_meas + mem[K_LP00] + LAT_OFFSET_FLOOR_RAD**2
        bias_y_var = LAT_BIAS_SIGMA0_MPS2**2 * exp(-mem[K_BIAS_Y_W] / LAT_BIAS_SETTLE_S) + LAT_BIAS_FLOOR_MPS2**2
        # the bias is the same at every sample: its variance counts once over the grid's memory, as every term's
        # systematic error does (docs/ESTIMATORS.md 11)
        sf = sqrt(ACCEL_NOISE_MPS2**2 + bias_y_var * _repeats(dt, v)) / G_MPS2
        lk = np.empty(NM)
        post = np.empty(NM * N_COMPLIANCE)
        comp = mem[K_KC : K_KC + N_COMPLIANCE]
        lateral_likelihood(
            MU_GRID, comp, understeer, kinematic, f_f, f_r, fx_f, fx_r, c_f, c_r, var0, sf, TEMPER, lk, post
        )
        for i in range(NM):
            for j in range(NC):
                like[i, j] = lk[i]
        if _apply(mem, like, 1.0, INCONSISTENT**TEMPER):
            # each mu's Kalman update, collapsed into one Gaussian by the posterior over mu: the tires are the car's
            _compliance_collapse(post, _mu_marginal(mem), comp)
    # calibration in calm driving: well below the proven friction, following the steer's linear reference
    if (
        at_limit
        or smp[S_TCS] + smp[S_ESC] > 0.0
        or abs(ay) > min(LAT_CALM_AY_MPS2, LAT_CALM_SHARE * G_MPS2 * mem[K_MU_LO])
        or abs(yaw_accel) > LAT_STEADY_YAW_ACCEL
    ):
        return
    k_us = mem[K_LAT_S] * understeer_gradient(c_f, c_r)
    r_ref = reference_yaw_rate(v, delta - mem[K_LAT_B], wb, k_us)
    if abs(smp[S_R] - r_ref) > LAT_REF_AGREE * abs(r_ref) + 0.02:
        return
    # forgetting widens the line's covariance back towards the prior's, never past it (a long straight has no
    # information on the slope: without the cap its variance would grow without bound, RLS's wind-up)
    # the line's regressor in the steady turn, a_y = v r (Rajamani eq. 3.15's K_us a_y): the yaw rate's noise is a
    # fortieth of the accelerometer's there, and a noisy regressor would pull the slope towards zero. Nearly straight
    # (|v r| under LAT_SLOPE_MIN_AY_MPS2) the regressor is mostly the gyro's noise: the offset alone learns there
    x_ss = v * smp[S_R] / G_MPS2 * (1.0 / c_f - 1.0 / c_r) if abs(v * smp[S_R]) >= LAT_SLOPE_MIN_AY_MPS2 else 0.0
    lam = exp(-dt / RLS_TAU_S)
    p00 = min(mem[K_LP00] / lam, LAT_OFFSET_SIGMA0_RAD**2)
    p11 = min(mem[K_LP11] / lam, LAT_SLOPE_SIGMA0**2)
    p01 = min(max(mem[K_LP01] / lam, -sqrt(p00 * p11)), sqrt(p00 * p11))
    ph0, ph1 = p00 + p01 * x_ss, p01 + p11 * x_ss
    den = ph0 + ph1 * x_ss + var_meas
    k0, k1 = ph0 / den, ph1 / den
    err = understeer - mem[K_LAT_S] * x_ss  # the offset is already out of `understeer`
    mem[K_LAT_B] += k0 * err
    mem[K_LAT_S] = min(max(mem[K_LAT_S] + k1 * err, LAT_SLOPE_RANGE[0]), LAT_SLOPE_RANGE[1])
    mem[K_LP00] = p00 - k0 * ph0
    mem[K_LP01] = p01 - k0 * ph1
    mem[K_LP11] = p11 - k1 * ph1
    mem[K_LAT_W] += dt


@njit(cache=True)
def pmf_step(mem, q, smp, t_prev, out):
    """One sample. Returns the sample's time (ms) to remember, or t_prev where the sample was rejected."""
    for k in range(N_BASE):
        if not np.isfinite(smp[k]):
            mem[K_REJECTED] += 1.0
            _output(mem, 0.0, 0.0, False, out)
            return t_prev
    dt = 0.0
    if mem[K_STARTED] == 0.0:
        _start(mem, True)
    else:
        dt = (smp[S_T] - t_prev) / 1000.0
        if not dt > 0.0:
            mem[K_REJECTED] += 1.0
            _output(mem, 0.0, 0.0, False, out)
            return t_prev
        if dt > MAX_STEP_S:
            mem[K_RESTARTS] += 1.0
            _start(mem, True)
            dt = 0.0
    if dt > 0.0:
        c_prior = np.empty(NC)
        _stiffness_prior(mem, q, c_prior)
        _compliance_forget(mem, dt)
        _predict(mem, dt, mem[K_V_REF], c_prior)
    radius = q[Q_RADIUS]
    # wheel ground speeds with the left/right radius ratios taken out (each side by half the ratio)
    v_wheels = np.empty(4)
    v_wheels[0] = smp[S_W0] * radius / (1.0 + 0.5 * mem[K_LR_F])
    v_wheels[1] = smp[S_W0 + 1] * radius * (1.0 + 0.5 * mem[K_LR_F])
    v_wheels[2] = smp[S_W0 + 2] * radius / (1.0 + 0.5 * mem[K_LR_R])
    v_wheels[3] = smp[S_W0 + 3] * radius * (1.0 + 0.5 * mem[K_LR_R])
    # what the car's motion explains: each wheel's speed mapped back to the CoG (wheel_kinematics), so that the inner
    # and outer wheels of a turn, and the front axle's larger radius, are not read as slip
    aty = smp[S_AY] / (1.0 + G_MPS2 * q[Q_ROLL])
    gain, offset, v_cog = np.empty(4), np.empty(4), np.empty(4)
    wheel_kinematics(q, smp[S_R], smp[S_SWA] / q[Q_STEER_RATIO], aty, gain, offset)
    for i in range(4):
        v_cog[i] = (v_wheels[i] - offset[i]) / gain[i]
    v_front = 0.5 * (v_cog[0] + v_cog[1])
    v_rear = 0.5 * (v_cog[2] + v_cog[3])
    drive = int(q[Q_DRIVE])
    v = v_rear if drive == 0 else (v_front if drive == 1 else 0.5 * (v_front + v_rear))
    v = abs(v)
    # the road's force per mass (guard.py), with the calibrated bias taken out
    bias_w = mem[K_BIAS_W]
    ax_c = smp[S_AX] - mem[K_BIAS]
    atx = ax_c + q[Q_DRAG] * v * v
    u = sqrt(atx * atx + aty * aty) / G_MPS2
    bias_sd = sqrt(BIAS_SIGMA0_MPS2**2 * exp(-bias_w / BIAS_TAU_S) + BIAS_SIGMA_FLOOR_MPS2**2)
    s_u = sqrt(ACCEL_NOISE_MPS2**2 + bias_sd**2) / G_MPS2
    like = np.empty((NM, NC))
    # the bound is a maximum, not a sum: only a utilisation above the largest recent one (aged as the grid forgets)
    # tells more; applying every sample's bound would count the same bias again and again
    u_seen = mem[K_U_SEEN] * exp(-_forget_rate(v) * dt)
    if u > u_seen:
        _bound_likelihood(u, u_seen, s_u, like)
        _apply(mem, like, 1.0)
        u_seen = u
    mem[K_U_SEEN] = u_seen
    # loads of the axles (static share and longitudinal transfer, eq. 2 summed over an axle)
    m, lf, lr, h = q[Q_M], q[Q_LF], q[Q_LR], q[Q_H]
    wb = lf + lr
    fz_front = m * (G_MPS2 * lr - atx * h) / wb
    fz_rear = m * (G_MPS2 * lf + atx * h) / wb
    # the reference speed (at the CoG), and wheels past their peak
    v_max, v_min = max(v_cog[0], v_cog[1], v_cog[2], v_cog[3]), min(v_cog[0], v_cog[1], v_cog[2], v_cog[3])
    v_ref = v_max if atx < 0.0 else v_min
    if dt > 0.0 and mem[K_V_REF] > 0.0 and v_max - v_min > REF_AGREE * v_max:  # wheels that agree are the reference
        tol = (REF_TOLERANCE_MPS2 + 2.0 * bias_sd) * dt
        v_ref = min(max(v_ref, mem[K_V_REF] + ax_c * dt - tol), mem[K_V_REF] + ax_c * dt + tol)
    mem[K_V_REF] = max(v_ref, 0.0)
    past_peak = False
    if v_ref >= SLIP_MIN_SPEED_MPS:
        for i in range(4):
            # the wheel's slip against the speed it rolls at without slip (eq. 6's form)
            kin = gain[i] * v_ref + offset[i]
            if abs(v_wheels[i] - kin) > LOCK_SLIP * max(abs(v_wheels[i]), abs(kin)):
                past_peak = True
    controller = smp[S_ABS] + smp[S_TCS] + smp[S_ESC] > 0.0
    limit = controller or past_peak
    # the optional channels (slip_slope.py): each axle's force (the force channels, else a_x), its slip against the
    # GNSS reference; the driven axle's term replaces the axle-slip term below where the reference speaks
    fx = np.empty(4)
    forces = ch.axle_forces(
        fx,
        smp[S_DRIVE],
        smp[S_BRAKE],
        q[Q_M],
        atx,
        s_u * G_MPS2,
        fz_front,
        fz_rear,
        q[Q_FRONT_DRIVE],
        q[Q_BRAKE_FRONT],
        q[Q_FRR],
    )
    straight = abs(smp[S_R]) * wb < 0.05 * max(v, 1.0) and abs(smp[S_SWA] / q[Q_STEER_RATIO]) < 0.05
    # slip between the front and the rear axle under braking (below): where it speaks it reads the wheels' slip, against
    # the car's own braking line, and the GNSS reference's per-axle terms stay silent (the same wheels, read once)
    share = q[Q_BRAKE_FRONT]
    brake = -m * atx - q[Q_FRR] * m * G_MPS2  # the brakes' force: the road's less the tires' rolling resistance
    braking_term = (
        dt > 0.0
        and straight
        and not limit
        and atx < -BRAKE_MIN_MPS2
        and brake > 0.0
        and 0.0 < share < 1.0
        and (mem[K_FR_W] if drive == 2 else mem[K_RLS_W]) >= FR_CALIBRATED_S
        and v_ref >= SLIP_MIN_SPEED_MPS
        and min(v_front, v_rear) > 0.5 * v_ref
    )
    ch.gnss_update(mem, K_CH, K_GB, smp[S_GNSS], smp[S_GNSS_ACC], ax_c, bias_sd, dt)
    v_x, v_x_sd = ch.reference_speed(mem, K_CH, smp[S_R], q[Q_LR], v, aty, q[Q_CA_REAR])
    gnss_driven = False
    if np.isfinite(v_x) and v_x >= SLIP_MIN_SPEED_MPS:
        calm = not limit and abs(smp[S_R]) * (q[Q_LF] + q[Q_LR]) < 0.05 * v_x
        evidence = not limit and not braking_term and dt > 0.0 and abs(aty) < ch.EVIDENCE_MAX_AY_MPS2
        s_floor = SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v_x
        for axle in range(2):
            c0 = q[Q_C0_FRONT] if axle == 0 else q[Q_C0_REAR]
            if ch.axle_slip_evidence(
                mem,
                K_CH,
                axle,
                dt,
                fx[axle],
                fx[2 + axle],
                v_front if axle == 0 else v_rear,
                v_x,
                v_x_sd,
                ax_c,
                calm,
                evidence,
                s_floor,
                SLIP_MODEL_SHARE,
                c0,
                MU_GRID,
                C_FACTORS,
                TEMPER,
                _repeats(dt, v),
                like,
            ):
                _apply(mem, like, 1.0, INCONSISTENT**TEMPER)
                gnss_driven = gnss_driven or axle == int(q[Q_DRIVE])
    if not limit:
        mem[K_U_LIMIT] = 0.0
    else:
        u_limit = u
        s_first = s_u
        if atx < 0.0:
            # braking: the axle whose brake share exceeds its load share reaches its limit first (ABS acts on it)
            share = q[Q_BRAKE_FRONT]
            fz_f, fz_r = max(fz_front, 0.2 * m * G_MPS2), max(fz_rear, 0.2 * m * G_MPS2)
            f_front = share * m * -atx / fz_f
            f_rear = (1.0 - share) * m * -atx / fz_r
            f_first = max(f_front, f_rear)
            u_limit = sqrt(f_first**2 + (aty / G_MPS2) ** 2)
            psi = (fz_f if f_front >= f_rear else fz_r) / (fz_f + fz_r)
            s_first = _axle_force_sd(f_first, -atx, s_u, psi)
        if smp[S_TCS] > 0.0 and smp[S_ABS] == 0.0 and drive < 2 and atx > 0.0:
            # traction control: only the driven axle is at its limit
            fz_d = max(fz_front if drive == 0 else fz_rear, 0.2 * m * G_MPS2)
            f_d = m * atx / fz_d
            u_limit = sqrt(f_d**2 + (aty / G_MPS2) ** 2)
            s_first = _axle_force_sd(f_d, atx, s_u, fz_d / (fz_front + fz_rear))
        # a controller's flag lags and latches (it stays on between the peaks of a sine steer): it speaks of the
        # largest utilisation of the last LIMIT_PEAK_S, not of this sample's
        u_limit = max(u_limit, mem[K_U_LIMIT] * exp(-dt / LIMIT_PEAK_S))
        mem[K_U_LIMIT] = u_limit
        if smp[S_ABS] > 0.0:
            # ABS: mu between the car's utilisation (both axles at their limit) and the first axle's (_abs_likelihood)
            _abs_likelihood(u, s_u, u_limit, s_first, q[Q_C0], like)
        elif smp[S_TCS] > 0.0 and atx > 0.0:
            _tcs_likelihood(u_limit, s_first, q[Q_C0], like)
        else:
            _limit_likelihood(u_limit, s_u, LIMIT_ESC if controller else LIMIT_LOCK, like)
        _apply(mem, like, TEMPER)
    # slip between the driven and the undriven axle (where a controller or a wheel past its peak speaks, its term reads
    # these wheels, once: a spinning wheel's slip says that the tire slides, not how stiff it is)
    driving = atx > -0.3 and smp[S_ABS] == 0.0
    f_d = 0.0
    s_raw = 0.0
    if drive < 2 and v >= SLIP_MIN_SPEED_MPS and min(v_front, v_rear) > 0.5 * v:
        v_d, v_u = (v_front, v_rear) if drive == 0 else (v_rear, v_front)
        fz_d, fz_u = (fz_front, fz_rear) if drive == 0 else (fz_rear, fz_front)
        s_raw = v_d / v_u - 1.0
        f_d = (m * atx + q[Q_FRR] * fz_u) / max(fz_d, 0.2 * m * G_MPS2)
        if forces:  # the drive force channel: the driven axle's force without the accelerometer's bias
            f_d = fx[drive]
        if straight and driving and not gnss_driven and not limit:
            _slip_likelihood(f_d, s_raw - mem[K_S0], v, q[Q_C0], like)
            _apply_at_stiffness(mem, like, INCONSISTENT**TEMPER)
    # slip between the front and the rear axle under braking (every drive; its condition `braking_term` above)
    if braking_term:
        fz_f, fz_r = max(fz_front, 0.2 * m * G_MPS2), max(fz_rear, 0.2 * m * G_MPS2)
        # the ratio's zero: an AWD's calm mean, a 2WD's slip line at no force (s0: driven over undriven axle)
        zero = mem[K_FR] if drive == 2 else (mem[K_S0] if drive == 0 else 1.0 / (1.0 + mem[K_S0]) - 1.0)
        d = -(v_front / v_rear - 1.0 - zero)  # braking slips: 1 - v_wheel / v, front minus rear
        x = brake / (m * G_MPS2)
        f_f, f_r = share * brake / fz_f, (1.0 - share) * brake / fz_r
        f_f_static, f_r_static = share * x * wb / lr, (1.0 - share) * x * wb / lf
        _brake_slip_likelihood(
            d,
            x,
            f_f,
            f_r,
            f_f_static,
            f_r_static,
            share,
            fz_f / (fz_f + fz_r),
            s_u * G_MPS2 / -atx,
            v_ref,
            q[Q_C0_FRONT],
            q[Q_C0_REAR],
            mem[K_BL_B] + mem[K_BL_K] * x,
            mem[K_BL_P00] + 2.0 * mem[K_BL_P01] * x + mem[K_BL_P11] * x * x
            if mem[K_BL_W] >= BRAKE_LINE_CALIBRATED_S
            else np.nan,
            _repeats(dt, v),
            like,
        )
        _apply_at_stiffness(mem, like, INCONSISTENT**TEMPER)
        age = mem[K_BL_AGE]
        mem[K_BL_AGE] = 0.0
        if x <= BRAKE_LINE_MAX_G:
            # the line at the static loads: the transfer's part (at the profile's tires) taken out
            transfer = (f_f - f_f_static) / q[Q_C0_FRONT] - (f_r - f_r_static) / q[Q_C0_REAR]
            x_f, d_f, settled = _line_input(mem, K_BL_X, x, d - transfer, dt, age)
            if settled:
                _line_update(mem, K_BL_B, x_f, d_f, dt, v_ref)
    else:
        mem[K_BL_AGE] = 0.0
    _lateral(mem, q, smp, dt, v, aty, atx, fz_front, fz_rear, like, past_peak)
    # the steering torques (aligning.py): the front axle's pneumatic trail against the brush model's at its force
    if al.torques_sent(smp[S_STEER_T], smp[S_EPS_T]) and dt > 0.0 and mem[K_V_PREV] >= 0.0:
        bias_y_sd = sqrt(LAT_BIAS_SIGMA0_MPS2**2 * exp(-mem[K_BIAS_Y_W] / LAT_BIAS_SETTLE_S) + LAT_BIAS_FLOOR_MPS2**2)
        f_al, _ = axle_lateral_per_load(
            m, lf, lr, q[Q_IZ], aty - mem[K_BIAS_Y], (smp[S_R] - mem[K_R_PREV]) / dt, fz_front, fz_rear
        )
        lk = np.empty(NM)
        if al.aligning_step(
            mem,
            K_AL,
            smp[S_STEER_T],
            smp[S_EPS_T],
            dt,
            (smp[S_SWA] / q[Q_STEER_RATIO] - mem[K_D_PREV]) / dt,
            f_al,
            fx[0],
            fz_front,
            sqrt(ACCEL_NOISE_MPS2**2 + bias_y_sd**2) / G_MPS2,
            q[Q_STEER_RATIO],
            q[Q_TRAIL_T0],
            q[Q_TRAIL_MECH],
            limit or smp[S_ABS] + smp[S_ESC] > 0.0 or v < ALIGNING_MIN_SPEED_MPS,
            MU_GRID,
            TEMPER,
            lk,
        ):
            for i in range(NM):
                for j in range(NC):
                    like[i, j] = lk[i]
            _apply(mem, like, 1.0, INCONSISTENT**TEMPER)
    _calibrate(mem, q, smp, dt, v_cog, gain, offset, v, ax_c, atx, f_d, s_raw, straight, driving)
    if dt > 0.0 and not controller and v >= SLIP_MIN_SPEED_MPS and straight:
        # the lateral accelerometer's bias: a_y - v r over straight driving (mounting roll; a road's crossfall too),
        # the mean of all so far until BIAS_TAU_S of them, then a moving average over that span
        w = max(1.0 - exp(-dt / BIAS_TAU_S), dt / (mem[K_BIAS_Y_W] + dt))
        mem[K_BIAS_Y] += w * ((aty - v * smp[S_R]) - mem[K_BIAS_Y])
        mem[K_BIAS_Y_W] += dt
    mem[K_R_PREV] = smp[S_R]
    mem[K_D_PREV] = smp[S_SWA] / q[Q_STEER_RATIO]
    mem[K_V_PREV] = v
    mem[K_U] = u
    mem[K_LIMIT] = 1.0 if limit else 0.0
    _output(mem, u, s_u, True, out)
    return smp[S_T]


@njit(cache=True)
def _evidence_interval(pm, lower, upper):
    """(lower, upper), widened to the grid cells whose evidence ratio pm / PRIOR is within LR_INTERVAL_RATIO of the
    largest (each cell read as a bin of one step, as _quantile reads it): where the evidence is silent about an end,
    or has aged back into the prior, that end is the grid's lowest cell (ice included) or PRIOR_UPPER_MU, the highest
    friction a road is taken to have (the guard's and the map's "nothing known above"). The walk keeps the prior's
    shape (WALK_UP, WALK_DOWN), so the ratio moves with evidence only."""
    half = 0.5 * (MU_GRID[1] - MU_GRID[0])
    best = 0.0
    for i in range(NM):
        best = max(best, pm[i] / PRIOR[i])
    for i in range(NM):
        if pm[i] / PRIOR[i] >= LR_INTERVAL_RATIO * best:
            lower = min(lower, MU_GRID[i] - half)
            break
    for i in range(NM - 1, -1, -1):
        if MU_GRID[i] - half < PRIOR_UPPER_MU and pm[i] / PRIOR[i] >= LR_INTERVAL_RATIO * best:
            upper = max(upper, min(MU_GRID[i] + half, PRIOR_UPPER_MU))
            break
    return lower, upper


@njit(cache=True)
def _output(mem, u, s_u, ok, out):
    if mem[K_STARTED] == 0.0:
        out[O_VALID] = 0.0
        return
    pm = _mu_marginal(mem)
    lower = _quantile(pm, 0.05)
    mu = _quantile(pm, 0.5)
    upper = _quantile(pm, 0.95)
    excited = u >= 0.5 * mu or mem[K_LIMIT] > 0.0 or upper - lower <= EXCITED_WIDTH
    if mem[K_U_SEEN] >= 0.5 * mu:
        # the car works its tires hard: the truth may lie right at the proven bound (the driver asked for more than
        # the road gave), which the posterior's smooth lower tail understates
        lower = min(lower, mem[K_U_SEEN] - 2.0 * s_u)
    if mem[K_LIMIT] > 0.0:  # likewise at a controller's or a sliding wheel's limit, for the acting axle
        lower = min(lower, mem[K_U_LIMIT] - 2.0 * s_u)
    out[O_MU] = mu
    mem[K_MU_LO] = max(lower, 0.0)  # the friction the car is taken to have (the lateral calibration's calm share)
    reported_lower, reported_upper = _evidence_interval(pm, lower, upper)  # what the evidence does not exclude
    out[O_LOWER] = max(reported_lower, 0.0)
    out[O_UPPER] = reported_upper
    out[O_EXCITED] = 1.0 if (ok and excited) else 0.0
    out[O_VALID] = 1.0


@njit(cache=True)
def run_rows(mem, q, samples, segments, out):
    """The step kernel over one vehicle's rows, restarting the mu grid where the segment id changes."""
    t_prev = 0.0
    for k in range(samples.shape[0]):
        if k > 0 and segments[k] != segments[k - 1]:
            mem[K_STARTED] = 0.0
            mem[K_RESTARTS] += 1.0
        t_prev = pmf_step(mem, q, samples[k], t_prev, out[k])


class PMFState:
    """One vehicle's filter: its profile, the packed parameters, the memory, and the last accepted time (ms)."""

    __slots__ = ("mem", "q", "t_prev", "vehicle")

    def __init__(self, vehicle: VehicleParams, q: np.ndarray, mem: np.ndarray, t_prev: float = 0.0):
        self.vehicle, self.q, self.mem, self.t_prev = vehicle, q, mem, t_prev


@njit(cache=True)
def step_rows(mem, q, samples, t_prev, out):
    """The step kernel over a run of one vehicle's rows from its state (`update_many`); the last accepted time (ms)."""
    for k in range(samples.shape[0]):
        t_prev = pmf_step(mem, q, samples[k], t_prev, out[k])
    return t_prev


_REQUIRED_COLUMNS = frozenset(c for c in SAMPLE_COLUMNS if c not in OPTIONAL_COLUMNS and c not in CHANNEL_COLUMNS)
_ALL_COLUMNS = frozenset(SAMPLE_COLUMNS)
_ROW = itemgetter(*SAMPLE_COLUMNS)


def _sample_values(sample: dict) -> tuple:
    """The values of SAMPLE_COLUMNS of one sample (a wire format v1 dict), None where not sent: an optional flag absent
    or null is 0 (not acting, as in the batch path), a channel absent or null None (NaN in the vector: not sent), a
    required field null None (NaN: the step rejects the sample); a sample lacking a required field is a ValueError."""
    keys = sample.keys()
    if _ALL_COLUMNS <= keys:  # the wire's samples: every name, None where not sent
        values = _ROW(sample)
    elif _REQUIRED_COLUMNS <= keys:
        values = tuple(sample.get(c) for c in SAMPLE_COLUMNS)
    else:
        missing = next(c for c in SAMPLE_COLUMNS if c in _REQUIRED_COLUMNS and c not in keys)
        raise ValueError(f"pmf: telemetry sample lacks the field {missing!r}")
    if values[S_TCS] is None or values[S_ESC] is None:
        values = (*values[:S_TCS], *(0.0 if v is None else v for v in values[S_TCS : S_ESC + 1]), *values[S_ESC + 1 :])
    return values


def _sample_matrix(samples) -> np.ndarray:
    """The rows step_rows reads, one per sample (_sample_values; None is NaN)."""
    return np.array([_sample_values(s) for s in samples], dtype=np.float64)


def _sample_vector(sample: dict) -> np.ndarray:
    """The row pmf_step reads for one sample (_sample_values; None is NaN)."""
    return np.array(_sample_values(sample), dtype=np.float64)


class PMFEstimator(Estimator):
    """mu from a Bayesian grid over (mu, tire stiffness): friction bound, controllers, axle slip (module doc)."""

    name = "pmf"

    def __init__(self, vehicle: VehicleParams | None = None):
        if vehicle is not None and not isinstance(vehicle, VehicleParams):
            raise TypeError(f"pmf: vehicle must be a VehicleParams, got {type(vehicle).__name__}")
        self.vehicle = vehicle

    def _vehicle(self, vehicle: VehicleParams | None) -> VehicleParams:
        return profile_of_call(vehicle, self.vehicle)

    def start(self, vehicle: VehicleParams | None = None) -> PMFState:
        vehicle = self._vehicle(vehicle)
        q = pack(vehicle)
        mem = np.zeros(N_MEM)
        init_memory(mem, q)
        return PMFState(vehicle, q, mem)

    def update(self, state: PMFState, sample: dict) -> Estimate | None:
        smp = _sample_vector(sample)
        out = np.zeros(N_OUT)
        state.t_prev = pmf_step(state.mem, state.q, smp, state.t_prev, out)
        if out[O_VALID] == 0.0 or not np.isfinite(smp[S_T]):
            return None
        return Estimate(
            str(sample["vehicle_id"]),
            int(smp[S_T]),
            float(out[O_MU]),
            float(out[O_LOWER]),
            float(out[O_UPPER]),
            bool(out[O_EXCITED]),
            self.name,
        )

    def update_many(self, state: PMFState, samples) -> EstimateRun:
        """`update` over a run in one kernel call (step_rows): the same state and estimates; a sample lacking a
        required field refuses the run before any of it is fed."""
        if not len(samples):
            return EstimateRun.of(())
        smp = _sample_matrix(samples)
        out = np.zeros((len(samples), N_OUT))
        state.t_prev = step_rows(state.mem, state.q, smp, state.t_prev, out)
        index = np.flatnonzero((out[:, O_VALID] != 0.0) & np.isfinite(smp[:, S_T]))
        judged = out[index]
        return EstimateRun(
            index,
            [str(samples[k]["vehicle_id"]) for k in index.tolist()],
            smp[index, S_T].astype(np.int64),
            judged[:, O_MU],
            judged[:, O_LOWER],
            judged[:, O_UPPER],
            judged[:, O_EXCITED] != 0.0,
            [self.name] * len(index),
        )

    def reset(self, state: PMFState) -> None:
        state.mem[K_STARTED] = 0.0

    def calibration(self, state: PMFState) -> dict:
        """The self-calibration this vehicle has reached, with the stiffness factor's posterior mean."""
        cm = _c_marginal(state.mem)
        out = {name: float(state.mem[k]) for name, k in CALIBRATION.items()}
        out["stiffness_factor"] = float(np.exp((cm * np.log(C_FACTORS)).sum() / cm.sum()))
        out["cornering_compliance_front"] = float(state.mem[K_KC])
        out["cornering_compliance_rear"] = float(state.mem[K_KC + 1])
        out["kinematic_angle_scale_error"] = float(state.mem[K_KC + 2])
        out["inconsistent"] = int(state.mem[K_INCONSISTENT])
        out["gnss_latency_s"] = float(state.mem[K_CH + ch.C_L])
        out["gnss_outliers"] = int(state.mem[K_CH + ch.C_OUTLIERS])
        for axle, name in ((0, "front"), (1, "rear")):
            line = K_CH + ch.C_LINE + axle * ch.N_LINE
            out[f"gnss_slip_offset_{name}"] = float(state.mem[line + ch.L_S0])  # the radius against GNSS
            out[f"gnss_slip_slope_{name}"] = float(state.mem[line + ch.L_K])  # Gustafsson's slope, 1 / C
            out[f"gnss_slip_line_weight_{name}_s"] = float(state.mem[line + ch.L_W])
        return out

    def state_to_dict(self, state: PMFState) -> dict:
        return {
            "estimator": self.name,
            "vehicle": state.vehicle.to_dict(),
            "memory": state.mem.tolist(),
            "t_prev": state.t_prev,
        }

    def state_from_dict(self, data: dict) -> PMFState:
        memory = data.get("memory")
        if isinstance(memory, list) and len(memory) in (
            N_MEM_V1,
            N_MEM_V2,
            N_MEM_V3,
            N_MEM_V4,
            N_MEM_V5,
            N_MEM_V6,
            N_MEM_V7,
        ):
            # saved before the optional channels' block (V1: the GNSS lock, latency and slip lines start afresh),
            # before the steering torques' (V2: the trail's gain at the profile's), before the slip line's input
            # filter (V3: empty), before the braking term (V4: its zero and line unlearned), before the reference
            # filter's accelerometer error (V5: none known), before the lateral state (V6) or with the compliances
            # alone in it (V7): everything else kept, each missing block fresh, as for a new car
            vehicle = VehicleParams.from_dict(data["vehicle"])
            q = pack(vehicle)
            block = np.zeros(N_MEM)
            init_appended_blocks(block, q)
            kept = memory[: min(len(memory), N_MEM_V6)]
            data = {**data, "memory": list(kept) + block[len(kept) :].tolist()}
        vehicle, memory = memory_state(data, self.name, N_MEM)
        return PMFState(vehicle, pack(vehicle), memory, float(data["t_prev"]))

    def estimate_batch(self, table: pa.Table, segments, vehicle: VehicleParams | None = None) -> pa.Table:
        vehicle = self._vehicle(vehicle)
        missing = [
            c
            for c in SAMPLE_COLUMNS
            if c not in table.column_names and c not in OPTIONAL_COLUMNS and c not in CHANNEL_COLUMNS
        ]
        if missing:
            raise ValueError(f"pmf: telemetry table lacks the column(s) {missing}")
        samples = np.zeros((table.num_rows, N_S))
        samples[:, N_BASE:] = np.nan  # a channel the table lacks is not sent
        for k, column in enumerate(SAMPLE_COLUMNS):
            if column in table.column_names:
                samples[:, k] = np.nan_to_num(
                    table[column].to_numpy(zero_copy_only=False).astype(np.float64),
                    nan=0.0 if column in OPTIONAL_COLUMNS else np.nan,
                )
        segments = np.asarray(segments)
        if segments.shape != (table.num_rows,):
            raise ValueError(f"segments must give one id per row ({table.num_rows}), got shape {segments.shape}")
        q = pack(vehicle)
        mem = np.zeros(N_MEM)
        init_memory(mem, q)
        out = np.zeros((table.num_rows, N_OUT))
        run_rows(mem, q, samples, segments.astype(np.int64), out)
        valid = out[:, O_VALID] > 0.0
        return estimate_table(
            {
                "vehicle_id": table["vehicle_id"].filter(pa.array(valid)),
                "timestamp_ms": table["timestamp_ms"].to_numpy()[valid],
                "mu": out[valid, O_MU],
                "mu_lower": out[valid, O_LOWER],
                "mu_upper": out[valid, O_UPPER],
                "excited": out[valid, O_EXCITED] > 0.0,
                "estimator": [self.name] * int(valid.sum()),
            }
        )
