"""Estimators judged by how hard the tires work: metrics in bins of true friction utilization.

An estimator's error means little pooled over samples: under steady driving mu is not observable and the honest answer
is a wide interval, while at the friction limit the estimate must be tight. So every metric is reported per bin of the
true utilization sqrt(a_x^2 + a_y^2) / (mu g) (true accelerations, true mu): < 0.3, 0.3-0.5, 0.5-0.8, >= 0.8, and a bin
of its own for samples with ABS acting (whatever their utilization). Per bin: RMSE and MAE of mu, coverage and mean
width of the 90 % interval, the share judged excited, and the share of samples whose mu lies below the tire-force bound
that the measured acceleration proves (estimators/guard.py), or below zero.
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.estimators.guard import GuardSettings, tire_force_bound
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.units import G_MPS2

UTILIZATION_BINS = (("< 0.3", 0.0, 0.3), ("0.3-0.5", 0.3, 0.5), ("0.5-0.8", 0.5, 0.8), (">= 0.8", 0.8, np.inf))
ABS_BIN = "ABS"
BIN_NAMES = tuple(name for name, _, _ in UTILIZATION_BINS) + (ABS_BIN,)


def utilization_bin(ax_true_mps2, ay_true_mps2, mu_true, abs_active) -> np.ndarray:
    """The bin name of each sample (ABS first, then the true utilization)."""
    utilization = np.hypot(ax_true_mps2, ay_true_mps2) / (np.maximum(mu_true, 0.05) * G_MPS2)
    names = np.empty(len(utilization), dtype=object)
    for name, low, high in UTILIZATION_BINS:
        names[(utilization >= low) & (utilization < high)] = name
    names[np.asarray(abs_active, dtype=bool)] = ABS_BIN
    return names


def binned_metrics(mu, lower, upper, excited, truth, bins, bound) -> list[dict]:
    """One row per bin (and 'all'): n, RMSE, MAE, coverage, width, judged excited, below the bound, negative."""
    mu, lower, upper, truth, bound = (np.asarray(a, dtype=np.float64) for a in (mu, lower, upper, truth, bound))
    excited = np.asarray(excited, dtype=bool)
    rows = []
    for name in BIN_NAMES + ("all",):
        m = np.ones(len(mu), dtype=bool) if name == "all" else bins == name
        n = int(m.sum())
        if n == 0:
            rows.append({"bin": name, "n": 0})
            continue
        rows.append(
            {
                "bin": name,
                "n": n,
                "rmse": rmse(mu[m], truth[m]),
                "mae": mae(mu[m], truth[m]),
                "coverage": float(((truth[m] >= lower[m]) & (truth[m] <= upper[m])).mean()),
                "width": float((upper[m] - lower[m]).mean()),
                "judged_excited": float(excited[m].mean()),
                "below_bound": float((mu[m] < bound[m] - 1e-9).mean()),
                "negative": int((lower[m] < 0.0).sum()),
            }
        )
    return rows


def estimates_on_runs(estimator, table: pa.Table, vehicles: dict, progress=None) -> dict[str, np.ndarray]:
    """Run a (streaming-capable) estimator over every run of a simulated table, each from its start with its own
    vehicle's profile; the estimates joined with the truth, as arrays over the estimated samples."""
    parts = []
    runs = table["run_id"].unique().to_pylist()
    for k, run_id in enumerate(runs):
        run = table.filter(pc.equal(table["run_id"], run_id))
        out = estimator.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), vehicles[run_id])
        rows = np.searchsorted(run["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
        col = {
            c: run[c].to_numpy(zero_copy_only=False)[rows]
            for c in (
                "mu",
                "ax_true_mps2",
                "ay_true_mps2",
                "abs_active",
                "accel_lon_mps2",
                "accel_lat_mps2",
                "speed_mps",
            )
        }
        col["bound"] = tire_force_bound(
            vehicles[run_id], col["accel_lon_mps2"], col["accel_lat_mps2"], col["speed_mps"], GuardSettings()
        )
        col |= {c: out[c].to_numpy(zero_copy_only=False) for c in ("mu_lower", "mu_upper", "excited")}
        col["mu_est"] = out["mu"].to_numpy()
        col["run_id"] = np.full(len(rows), run_id, dtype=object)
        parts.append(col)
        if progress:
            progress(k + 1, len(runs))
    return {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def estimator_bins(estimates: dict[str, np.ndarray]) -> list[dict]:
    """binned_metrics of estimates_on_runs' output."""
    e = estimates
    bins = utilization_bin(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"], e["abs_active"])
    return binned_metrics(e["mu_est"], e["mu_lower"], e["mu_upper"], e["excited"], e["mu"], bins, e["bound"])


BIN_ESTIMATORS = ("pmf", "ekf", "ukf", "default")


def run_bins_benchmark(seed: int = 0, estimators=BIN_ESTIMATORS, progress=None) -> list[dict]:
    """Every estimator (as `load_estimator` gives it: guarded) on the generalization benchmark's test runs (held-out
    vehicle and mu bands, every production-terminal effect on), by utilization bin: one row per (estimator, bin)."""
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.sim.presets import generalization_scenarios
    from roadgrip.sim.simulate import simulate

    scenarios = generalization_scenarios("test", seed)
    table = simulate(scenarios)
    vehicles = {s.run_id: s.vehicle for s in scenarios}
    rows = []
    for name in estimators:
        if progress:
            progress(f"{name} on {len(scenarios)} test runs by utilization bin")
        estimates = estimates_on_runs(load_estimator(name), table, vehicles)
        rows += [{"estimator": name} | row for row in estimator_bins(estimates)]
    return rows


def bins_markdown(rows: list[dict]) -> str:
    """The per-bin table: one line per estimator and bin."""
    lines = [
        "| estimator | bin | n | RMSE | MAE | 90 % coverage | width | judged excited | below bound | negative |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["n"] == 0:
            lines.append(f"| {r['estimator']} | {r['bin']} | 0 | - | - | - | - | - | - | - |")
            continue
        lines.append(
            f"| {r['estimator']} | {r['bin']} | {r['n']} | {r['rmse']:.3f} | {r['mae']:.3f} | "
            f"{r['coverage']:.2f} | {r['width']:.2f} | {r['judged_excited']:.2f} | "
            f"{r['below_bound']:.3f} | {r['negative']} |"
        )
    return "\n".join(lines) + "\n"
