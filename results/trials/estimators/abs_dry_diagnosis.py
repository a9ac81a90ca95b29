"""Where pmf's error under ABS comes from (issue 23; docs/RESULTS.md, "ABS: the brake demand unknown"). Validation
split only (the test split is looked at once, by the lead).

    PYTHONPATH=. python results/trials/estimators/abs_dry_diagnosis.py

On every sample of the split's runs with ABS acting, by mu band: the true mu against what the ABS path reads from the
catalogue profile (bins.catalogue_profile, as the benchmark gives it), from the true accelerations, so that the
sensors' noise and bias do not hide the physics:
- u_car = sqrt(a_x^2 + a_y^2) / g, the car's utilisation: mu when both axles are at their limit;
- u_first, the utilisation of the axle that the profile's brake_front_share saturates first (pmf's u_limit before
  issue 23's change), and the same latched as pmf latches it (the largest of the last LIMIT_PEAK_S, fading): mu when
  only that axle is at its limit;
- p, the true force per load of the more utilised axle (the simulator's |fx| / fz summed over each axle): what ABS
  holds, mu for a stiff tire;
- the front load share of the profile against the drawn car's (static);
and pmf's (guarded, as the benchmark runs it) median and 90 % interval: RMSE, coverage, median error, and the share of
samples whose guard bound (mu_proven) lies above the true mu (there the interval cannot cover).
"""

from __future__ import annotations

import numpy as np
import pyarrow.compute as pc

from roadgrip.units import G_MPS2


def _axle(run, names):
    fx = sum(np.abs(run[f"fx_{w}_n"].to_numpy()) for w in names)
    fz = sum(run[f"fz_{w}_n"].to_numpy() for w in names)
    return fx / np.maximum(fz, 1.0)


def _utilisations(run, profile):
    """(u_car, u_first, front axle first) of every row from the true accelerations and the profile."""
    ax, ay = run["ax_true_mps2"].to_numpy(), run["ay_true_mps2"].to_numpy()
    m, lf, lr, h = profile.mass_kg, profile.cg_to_front_axle_m, profile.cg_to_rear_axle_m, profile.cg_height_m
    wb = lf + lr
    fz_f = np.maximum(m * (G_MPS2 * lr - ax * h) / wb, 0.2 * m * G_MPS2)
    fz_r = np.maximum(m * (G_MPS2 * lf + ax * h) / wb, 0.2 * m * G_MPS2)
    share = profile.brake_front_share
    f_front, f_rear = share * m * np.maximum(-ax, 0.0) / fz_f, (1.0 - share) * m * np.maximum(-ax, 0.0) / fz_r
    return np.hypot(ax, ay) / G_MPS2, np.hypot(np.maximum(f_front, f_rear), ay / G_MPS2), f_front >= f_rear


def _latched(values, t, rows, peak_s):
    return np.array([np.max(values[: r + 1] * np.exp(-(t[r] - t[: r + 1]) / peak_s)) for r in rows])


def _pct(x):
    lo, mid, hi = np.percentile(x, (5, 50, 95))
    return f"{lo:.2f}-{mid:.2f}-{hi:.2f}"


def main() -> None:
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.estimators.pmf import LIMIT_PEAK_S
    from roadgrip.evaluation.physics_benchmark import BAND_NAMES, mu_band, simulate_split

    split = simulate_split("validation")
    table = split.tables[None][0]
    names = ("mu", "u_car", "u_first", "u_first_latched", "p", "front", "front_true", "share_err", "est", "lo", "hi")
    cols = {k: [] for k in names + ("bound",)}
    for scenario, _ in split.drawn:
        run = table.filter(pc.equal(table["run_id"], scenario.run_id))
        rows = np.flatnonzero(run["abs_active"].to_numpy(zero_copy_only=False))
        if not rows.size:
            continue
        profile = split.profiles[scenario.run_id]
        out = load_estimator("pmf").estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), profile)
        at = np.searchsorted(out["timestamp_ms"].to_numpy(), run["timestamp_ms"].to_numpy()[rows])
        u_car, u_first, front = _utilisations(run, profile)
        f_front, f_rear = _axle(run, ("fl", "fr")), _axle(run, ("rl", "rr"))
        drawn_share = scenario.vehicle.cg_to_rear_axle_m / scenario.vehicle.wheelbase_m
        part = {
            "mu": run["mu"].to_numpy()[rows],
            "u_car": u_car[rows],
            "u_first": u_first[rows],
            "u_first_latched": _latched(u_first, run["t_s"].to_numpy(), rows, LIMIT_PEAK_S),
            "p": np.maximum(f_front, f_rear)[rows],
            "front": front[rows],
            "front_true": (f_front >= f_rear)[rows],
            "share_err": np.full(rows.size, profile.cg_to_rear_axle_m / profile.wheelbase_m - drawn_share),
            "est": out["mu"].to_numpy()[at],
            "lo": out["mu_lower"].to_numpy()[at],
            "hi": out["mu_upper"].to_numpy()[at],
            "bound": out["mu_proven"].to_numpy()[at],
        }
        for k, v in part.items():
            cols[k].append(v)
    c = {k: np.concatenate(v) for k, v in cols.items()}
    bands = mu_band(c["mu"])
    print(f"{c['mu'].size} ABS samples on the validation split (5-50-95 % where three numbers)\n")
    print(
        "| band | n | mu / u_car | mu / u_first | mu / u_first latched | mu in [u_car, u_first latched] | p / mu | "
        "front first (profile / truth) | front load share, profile - drawn |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    for band in BAND_NAMES + ("all",):
        k = np.ones(bands.size, dtype=bool) if band == "all" else bands == band
        mu = c["mu"][k]
        inside = np.mean((mu >= c["u_car"][k]) & (mu <= c["u_first_latched"][k]))
        print(
            f"| {band} | {k.sum()} | {_pct(mu / c['u_car'][k])} | {_pct(mu / c['u_first'][k])} | "
            f"{_pct(mu / c['u_first_latched'][k])} | {inside:.2f} | {_pct(c['p'][k] / mu)} | "
            f"{np.mean(c['front'][k]):.2f} / {np.mean(c['front_true'][k]):.2f} | {_pct(c['share_err'][k])} |"
        )
    print("\n| band | pmf RMSE | pmf coverage | pmf median - mu | mu above pmf's upper | guard bound above mu |")
    print("|---|---|---|---|---|---|")
    for band in BAND_NAMES + ("all",):
        k = np.ones(bands.size, dtype=bool) if band == "all" else bands == band
        mu, err = c["mu"][k], c["est"][k] - c["mu"][k]
        cover = np.mean((mu >= c["lo"][k]) & (mu <= c["hi"][k]))
        print(
            f"| {band} | {np.sqrt(np.mean(err**2)):.3f} | {cover:.2f} | {_pct(err)} | "
            f"{np.mean(mu > c['hi'][k]):.2f} | {np.mean(c['bound'][k] > mu):.2f} |"
        )


if __name__ == "__main__":
    main()
