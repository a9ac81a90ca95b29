"""Per run of the physics validation split's steers and tight turns: pmf's RMSE, coverage and lowest mu_upper, with the
drawn tire's stiffness factor, the understeer line's slope and (with lateral_compliance_state.diff applied, which
reports them) the front and rear tires' compliances at the run's end (docs/RESULTS.md, "The tires' compliance as a
state the samples share").

    PYTHONPATH=<tree> python results/trials/estimators/lateral_compliance_grid.py OUT.json
"""

from __future__ import annotations

import json
import sys

import numpy as np

from roadgrip.estimators.pmf import PMFEstimator
from roadgrip.evaluation.bins import catalogue_profile
from roadgrip.sim.presets import physics_benchmark_runs
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2

KEEP = ("ramp_steer", "sine_steer", "tight_turn")


def main(path: str) -> None:
    drawn = [(s, e) for s, e in physics_benchmark_runs("validation") if s.manoeuvre in KEEP]
    table = simulate([s for s, _ in drawn])
    est = PMFEstimator()
    out = {}
    for scenario, entry in drawn:
        run = table.filter(np.asarray(table["run_id"].to_numpy(zero_copy_only=False) == scenario.run_id))
        profile = catalogue_profile(entry, scenario.vehicle)
        state = est.start(profile)
        res = est.update_many(state, run.to_pylist())
        mu_true = run["mu"].to_numpy()[res.index]
        u = np.hypot(run["ax_true_mps2"].to_numpy(), run["ay_true_mps2"].to_numpy())[res.index] / (mu_true * G_MPS2)
        cal = est.calibration(state)
        out[scenario.run_id] = {
            "manoeuvre": scenario.manoeuvre,
            "vehicle": scenario.vehicle.name,
            "tire": scenario.tire.name,
            "stiffness_scale": scenario.tire.stiffness_scale,
            "mu": float(mu_true[0]),
            "u_max": float(u.max()),
            "rmse": float(np.sqrt(np.mean((res.mu - mu_true) ** 2))),
            "coverage": float(np.mean((res.mu_lower <= mu_true) & (mu_true <= res.mu_upper))),
            "upper_min": float(res.mu_upper.min()),
            "upper_end": float(res.mu_upper[-1]),
            "k_line": cal["cornering_compliance_factor"],
            "k_front": cal.get("cornering_compliance_front", 1.0),
            "k_rear": cal.get("cornering_compliance_rear", 1.0),
        }
    with open(path, "w") as f:
        json.dump(out, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1])
