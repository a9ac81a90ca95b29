"""How much the understeer angle says of mu over a whole run, by the tire curve read: the run's own (the simulator's),
the brush model's (pmf's, lateral.py), or a family of curves the run must choose among.

Per physics validation run (ramp steer, sine steer, tight turn), every sample with v > 3 m/s and a road-wheel angle under
0.15 rad: the understeer angle y = delta - L r / v from the sent steering angle and yaw rate, and each axle's lateral
force per load f_f, f_r from the sent a_y and the yaw acceleration (Newton-Euler at the catalogue profile's geometry,
lateral.py `axle_lateral_per_load`). For each grid mu the model

    y = b + k_f alpha(f_f; mu, c_f) - k_r alpha(f_r; mu, c_r) + noise (SIGMA)

with alpha the curve's slip angle at the catalogue's cornering stiffness per load c, is linear in the nuisance
(b: the steering and gyro offsets, 1 sigma 0.002 rad; k_f, k_r: each axle's compliance over the catalogue's, 1 +- 0.36,
correlated 0.69: the +-30 % common and +-20 % per-axle spread the presets draw), so its marginal likelihood is Gaussian
in closed form; a sample beyond an axle's limit at that mu rules it out (the friction bound's part). With several
curves (--shapes brush,dugoff,mf) the likelihood of each mu is their mixture, equal prior weights, the curve shared by
the run's samples. Printed: per run the best mu and the 90 % likelihood-ratio interval; per band how often the interval
holds the truth and excludes the other side (ice: mu 0.8 excluded; dry: mu 0.3 excluded).

    PYTHONPATH=<checkout> nice -n 19 python results/trials/estimators/lateral_shape_identifiability.py --shapes own
    ... --shapes brush | --shapes brush,dugoff,mf [--sigma 0.0008]

Validation split only (never the test split). Offline: no estimator state, no forgetting; the whole run at once."""

import argparse
import dataclasses

import numpy as np

MUS = np.arange(0.075, 1.401, 0.025)
LR90 = 2.705543 / 2
PRIOR_COV = np.array([[0.002**2, 0.0, 0.0], [0.0, 0.13, 0.09], [0.0, 0.09, 0.13]])  # b, k_f, k_r


def _curve(tire):
    """(f / mu, c tan(alpha) / mu) of a tire model up to its peak, for interpolation (the curve's shape alone)."""
    from roadgrip.vehicle.params import TireParams

    x = np.linspace(0.0, 1.5, 6000)
    fy = tire.forces(TireParams(10.0, 10.0 / tire.stiffness_scale, 0.04), 0.0, np.arctan(x / 10.0), 1000.0, 1.0)[1]
    peak = int(np.argmax(fy)) + 1
    return fy[:peak] / 1000.0, x[:peak]


def _shape(name, scenario):
    from roadgrip.vehicle.tires.dugoff import DugoffTire
    from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

    if name == "brush":
        return None
    return _curve({"own": scenario.tire, "dugoff": DugoffTire(), "mf": MagicFormulaTire()}[name])


def _alpha(f, mu, c, curve):
    """The curve's slip angle (tan) at force per load f on mu; nan beyond the limit."""
    x = np.abs(f) / mu
    if curve is None:
        a = 3.0 * mu / c * (1.0 - np.cbrt(np.clip(1.0 - x, 0.0, None)))
    else:
        a = np.interp(x, curve[0], curve[1]) * mu / c
    a[x >= (1.0 if curve is None else curve[0][-1])] = np.nan
    return np.sign(f) * a


def _loglik(y, ff, fr, cf, cr, curve, sigma):
    out = np.empty(MUS.size)
    for i, mu in enumerate(MUS):
        af, ar = _alpha(ff, mu, cf, curve), _alpha(fr, mu, cr, curve)
        if not (np.isfinite(af).all() and np.isfinite(ar).all()):
            out[i] = -np.inf
            continue
        h = np.stack([np.ones(y.size), af, -ar], 1)
        cov = h @ PRIOR_COV @ h.T + sigma**2 * np.eye(y.size)
        res = y - h @ np.array([0.0, 1.0, 1.0])
        out[i] = -0.5 * (res @ np.linalg.solve(cov, res) + np.linalg.slogdet(cov)[1])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--shapes", default="own")
    parser.add_argument("--sigma", type=float, default=0.0008, help="the understeer angle's noise per sample (rad)")
    args = parser.parse_args()
    from roadgrip.estimators import pmf
    from roadgrip.evaluation.physics_benchmark import catalogue_profile
    from roadgrip.sim.presets import physics_benchmark_runs
    from roadgrip.sim.simulate import simulate

    drawn = [
        (s, e)
        for s, e in physics_benchmark_runs("validation", None)
        if s.manoeuvre in ("ramp_steer", "sine_steer", "tight_turn")
    ]
    table = simulate([dataclasses.replace(s, effects=s.effects.with_channels()) for s, _ in drawn]).to_pydict()
    ids = np.array(table["run_id"])
    tally = {"ice": [0, 0, 0], "dry": [0, 0, 0]}
    for s, entry in drawn:
        q = pmf.pack(catalogue_profile(entry, s.vehicle))
        m, lf, lr, iz, ratio = q[pmf.Q_M], q[pmf.Q_LF], q[pmf.Q_LR], q[pmf.Q_IZ], q[pmf.Q_STEER_RATIO]
        wb = lf + lr
        rows = ids == s.run_id
        col = {
            k: np.asarray(table[k], float)[rows]
            for k in ("t_s", "speed_mps", "yaw_rate_radps", "accel_lat_mps2", "steering_wheel_angle_rad", "mu_fl")
        }
        v, r, delta = col["speed_mps"], col["yaw_rate_radps"], col["steering_wheel_angle_rad"] / ratio
        ok = (v > 3.0) & (np.abs(delta) < 0.15)
        mu_true = float(col["mu_fl"].mean())
        if ok.sum() < 10:
            continue
        r_dot = np.gradient(r, col["t_s"])
        ay = col["accel_lat_mps2"]
        ff = ((m * lr * ay + iz * r_dot) / wb / (m * 9.81 * lr / wb))[ok]
        fr = ((m * lf * ay - iz * r_dot) / wb / (m * 9.81 * lf / wb))[ok]
        y = (delta - wb * r / v)[ok]
        lls = [
            _loglik(y, ff, fr, q[pmf.Q_CA_FRONT], q[pmf.Q_CA_REAR], _shape(name, s), args.sigma)
            for name in args.shapes.split(",")
        ]
        ll = np.logaddexp.reduce(np.array(lls), axis=0)
        ll -= ll.max()
        inside = MUS[ll > -LR90]
        band = "ice" if mu_true <= 0.3 else ("dry" if mu_true >= 0.6 else None)
        print(
            f"{s.run_id} {s.tire.name:13s} {s.manoeuvre:10s} mu {mu_true:.2f} u_max {np.abs(ay[ok]).max() / 9.81 / mu_true:.2f} best {MUS[np.argmax(ll)]:.2f} LR90 [{inside.min():.2f}, {inside.max():.2f}]"
        )
        if band:
            t = tally[band]
            t[0] += 1
            t[1] += int(inside.min() - 0.0125 <= mu_true <= inside.max() + 0.0125)
            t[2] += int(inside.max() < 0.8) if band == "ice" else int(inside.min() > 0.3)
    for band, (n, held, told) in tally.items():
        other = "0.8" if band == "ice" else "0.3"
        print(f"{band}: {n} runs; the interval holds the truth in {held}, excludes {other} in {told}")


if __name__ == "__main__":
    main()
