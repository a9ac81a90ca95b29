"""What pmf's lateral channel can see before its understeer line is calibrated (issue 23, item 1; docs/RESULTS.md,
"The lateral channel with a correlated stiffness spread: tried, not adopted").

    python results/trials/estimators/lateral_before_calibration.py observability
        the brush model's bend of the understeer angle over its line, against the spread of that line before
        calibration (the tires' stiffness: +-30 % common to both axles, +-10 % each axle's own), for the catalogue
        profiles at 50 / 80 / 95 % of the limit on mu 0.15 and 1.0 (closed form, no simulation)
    python results/trials/estimators/lateral_before_calibration.py line
        how far the validation split's ramp and sine steers on ice and snow calibrate the line themselves: the slope's
        1-sigma (RLS, pmf.K_LP11; 0.3 fresh) when the tires first reach half their limit, and at the run's end
    python results/trials/estimators/lateral_before_calibration.py steer-cells [validation|test]
        the ramp and sine steers of a physics-benchmark split by mu band and utilization bin, prior and pmf (the
        benchmark's own tables hold manoeuvres over all bins only)
"""

from __future__ import annotations

import sys

import numpy as np

from roadgrip.units import G_MPS2

COMMON, PER_AXLE = 0.3, 0.1


def observability() -> None:
    from roadgrip.estimators.lateral import brush_slip
    from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV

    print("| profile | mu | u | line (mrad) | bend over it (mrad) | line's spread (mrad) | bend / spread |")
    print("|---|---|---|---|---|---|---|")
    for p in (PAPER_SUV, MIDSIZE_SEDAN, COMPACT_HATCHBACK):
        c_f = p.tire_front.cornering_stiffness_per_load_per_rad
        c_r = p.tire_rear.cornering_stiffness_per_load_per_rad
        for mu in (0.15, 1.0):
            for u in (0.5, 0.8, 0.95):
                f = u * mu  # a steady turn: both axles at the same force per load
                line = f / c_f - f / c_r
                bend = brush_slip(f, mu, c_f) - brush_slip(f, mu, c_r) - line
                spread = np.sqrt((COMMON * line) ** 2 + (PER_AXLE * f / c_f) ** 2 + (PER_AXLE * f / c_r) ** 2)
                print(
                    f"| {p.name} | {mu} | {u} | {1e3 * line:.2f} | {1e3 * bend:.2f} | {1e3 * spread:.2f} "
                    f"| {bend / spread:.1f} |"
                )


def _steers(split: str, surfaces=None):
    from roadgrip.evaluation.bins import catalogue_profile
    from roadgrip.sim.presets import physics_benchmark_runs
    from roadgrip.sim.simulate import simulate

    drawn = [
        (s, e)
        for s, e in physics_benchmark_runs(split)
        if s.manoeuvre in ("ramp_steer", "sine_steer") and (surfaces is None or s.condition in surfaces)
    ]
    table = simulate([s for s, _ in drawn])
    return drawn, table, {s.run_id: catalogue_profile(e, s.vehicle) for s, e in drawn}


def line() -> None:
    import pyarrow.compute as pc

    from roadgrip.estimators import pmf

    drawn, table, profiles = _steers("validation", ("ice", "snow"))
    print("| run | manoeuvre | mu | max u | slope's sigma at u >= 0.5 | at the end | slope there |")
    print("|---|---|---|---|---|---|---|")
    for s, _ in drawn:
        rows = table.filter(pc.equal(table["run_id"], s.run_id)).to_pylist()
        est = pmf.PMFEstimator()
        state = est.start(profiles[s.run_id])
        mu = rows[0]["mu"]
        sigma, slope, u = [], [], []
        for r in rows:
            est.update(state, r)
            sigma.append(np.sqrt(state.mem[pmf.K_LP11]))
            slope.append(state.mem[pmf.K_LAT_S])
            u.append(abs(r["ay_true_mps2"]) / (mu * G_MPS2))
        u = np.array(u)
        if not (u >= 0.5).any():
            continue
        i = int(np.argmax(u >= 0.5))
        print(
            f"| {s.run_id} | {s.manoeuvre} | {mu:.2f} | {u.max():.2f} | {sigma[i]:.2f} | {sigma[-1]:.2f} "
            f"| {slope[i]:.2f} |"
        )


def steer_cells(split: str) -> None:
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.evaluation.baseline import prior_baseline
    from roadgrip.evaluation.bins import estimates_on_runs, prior_estimates
    from roadgrip.evaluation.physics_benchmark import cell_metrics

    _, table, profiles = _steers(split)
    baseline_mu = prior_baseline().mu_median
    print("| estimator | mu band | utilization | RMSE / skill / coverage (samples) |")
    print("|---|---|---|---|")
    for name in ("prior", "pmf"):
        if name == "prior":
            estimates = prior_estimates(table, profiles)
        else:
            estimates = estimates_on_runs(load_estimator(name), table, profiles)
        for r in cell_metrics(estimates, baseline_mu):
            if r.get("rmse") is not None and r["band"] in ("<= 0.3", ">= 0.6", "all"):
                print(
                    f"| {name} | {r['band']} | {r['bin']} "
                    f"| {r['rmse']:.3f} / {r['skill']:+.2f} / {r['coverage']:.2f} ({r['n']}) |"
                )


if __name__ == "__main__":
    what = sys.argv[1] if len(sys.argv) > 1 else "observability"
    if what == "observability":
        observability()
    elif what == "line":
        line()
    elif what == "steer-cells":
        steer_cells(sys.argv[2] if len(sys.argv) > 2 else "validation")
    else:
        raise SystemExit(f"unknown part {what!r}: observability | line | steer-cells [split]")
