"""The physics estimators on benchmark test data: no training, each run filtered from its start with its vehicle's
profile, as `load_estimator` gives them (with the physics guard, as the product runs them)."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.estimators.learned import load_estimator
from roadgrip.training.fit import PreparedData

PHYSICS_ROWS = {"pmf": "pmf", "ekf": "EKF", "ukf": "UKF"}  # estimator name: name in the tables


def physics_on_runs(name: str, table: pa.Table, vehicles: dict, test: PreparedData):
    """(mu, lower, upper) of a physics filter at the test windows' last samples; each run filtered from its start with
    its own vehicle's profile (the profile of a fleet's car is known: CONTRACTS 3.2)."""
    estimator = load_estimator(name)
    found = {}
    for run_id in np.unique(test.runs):
        run = table.filter(pc.equal(table["run_id"], run_id))
        out = estimator.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), vehicles[run_id])
        keys = zip([run_id] * run.num_rows, np.round(run["t_s"].to_numpy(), 3))
        found.update(zip(keys, zip(*(out[c].to_numpy() for c in ("mu", "mu_lower", "mu_upper")))))
    rows = np.array([found[(r, round(t, 3))] for r, t in zip(test.runs, test.t_s)])
    return rows[:, 0], rows[:, 1], rows[:, 2]
