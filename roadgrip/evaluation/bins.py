"""Estimators judged by how hard the tires work: metrics in bins of true friction utilization.

An estimator's error means little pooled over samples: under steady driving mu is not observable and the honest answer
is a wide interval, while at the friction limit the estimate must be tight. So every metric is reported per bin of the
true utilization sqrt(a_x^2 + a_y^2) / (mu g) (true accelerations, true mu): < 0.3, 0.3-0.5, 0.5-0.8, >= 0.8, and a bin
of its own for samples with ABS acting (whatever their utilization). Per bin: RMSE and MAE of mu, coverage and mean
width of the 90 % interval, the share judged excited, and the share of samples whose mu lies below the tire-force bound
that the measured acceleration proves (estimators/guard.py), or below zero; given the prior baseline's estimate
(evaluation/baseline.py), its RMSE over the same samples and the skill against it.

The estimator gets the profile a fleet registers for a car: the catalogue entry (vehicle/params.py VEHICLES) its drawn
vehicle came from, with the drawn drive layout (catalogue_profile), never the simulator's drawn mass, radius or
stiffness. The bound a metric checks is the one the measured acceleration proves with that profile (what the guard
and a fleet can know; with the drawn vehicle's drag and roll the guarded estimators' mu falls a hair below it).
"""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.estimators.guard import GuardSettings, tire_force_bound
from roadgrip.evaluation.baseline import PRIOR_NAME, PriorBaseline, prior_baseline, skill
from roadgrip.evaluation.metrics import mae, rmse
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import VehicleParams

UTILIZATION_BINS = (("< 0.3", 0.0, 0.3), ("0.3-0.5", 0.3, 0.5), ("0.5-0.8", 0.5, 0.8), (">= 0.8", 0.8, np.inf))
ABS_BIN = "ABS"
BIN_NAMES = tuple(name for name, _, _ in UTILIZATION_BINS) + (ABS_BIN,)


def true_utilization(ax_true_mps2, ay_true_mps2, mu_true) -> np.ndarray:
    """How hard the tires work, the truth's view: |a| / (mu g) of the true accelerations and mu (mu floored at 0.05).
    Never the reported accelerations: on ice a sensor's noise and bias alone read as half the limit."""
    return np.hypot(ax_true_mps2, ay_true_mps2) / (np.maximum(mu_true, 0.05) * G_MPS2)


def utilization_bin(ax_true_mps2, ay_true_mps2, mu_true, abs_active) -> np.ndarray:
    """The bin name of each sample (ABS first, then the true utilization)."""
    utilization = true_utilization(ax_true_mps2, ay_true_mps2, mu_true)
    names = np.empty(len(utilization), dtype=object)
    for name, low, high in UTILIZATION_BINS:
        names[(utilization >= low) & (utilization < high)] = name
    names[np.asarray(abs_active, dtype=bool)] = ABS_BIN
    return names


def binned_metrics(mu, lower, upper, excited, truth, bins, bound, baseline_mu: float | None = None) -> list[dict]:
    """One row per bin (and 'all'): n, RMSE, MAE, coverage, width, judged excited, below the bound, negative; with a
    baseline_mu also the constant baseline's RMSE on the bin's samples (prior_rmse) and the skill against it."""
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
        if baseline_mu is not None:
            rows[-1]["prior_rmse"] = rmse(np.full(n, baseline_mu), truth[m])
            rows[-1]["skill"] = skill(rows[-1]["rmse"], rows[-1]["prior_rmse"])
    return rows


def catalogue_profile(entry: VehicleParams, drawn: VehicleParams) -> VehicleParams:
    """The profile a fleet knows of a car drawn around a catalogue entry: the entry's nominal values (mass, radius,
    stiffness, geometry) with the drawn car's drive layout (the variant it registers; an AWD's split nominal)."""
    if drawn.drive == entry.drive:
        return entry.replace(name=drawn.name)
    share = {"fwd": 1.0, "rwd": 0.0, "awd": 0.5}[drawn.drive]
    return entry.replace(name=drawn.name, drive=drawn.drive, front_drive_share=share)


TRUTH_COLUMNS = ("mu", "ax_true_mps2", "ay_true_mps2", "abs_active", "accel_lon_mps2", "accel_lat_mps2", "speed_mps")


def _truth_at(run: pa.Table, rows, vehicle: VehicleParams, run_id) -> dict[str, np.ndarray]:
    """The truth and the signals of a run at the given rows, with the bound the measured acceleration proves."""
    col = {c: run[c].to_numpy(zero_copy_only=False)[rows] for c in TRUTH_COLUMNS}
    col["bound"] = tire_force_bound(
        vehicle, col["accel_lon_mps2"], col["accel_lat_mps2"], col["speed_mps"], GuardSettings()
    )
    col["run_id"] = np.full(len(rows), run_id, dtype=object)
    return col


def _runs(table: pa.Table):
    for run_id in table["run_id"].unique().to_pylist():
        yield run_id, table.filter(pc.equal(table["run_id"], run_id))


LEAD_IN_GAP_S = 600.0  # a lead-in ends this long before its run starts: the car parked, then a new trip


def _after_lead_in(run: pa.Table, lead: pa.Table) -> tuple[pa.Table, np.ndarray]:
    """The lead-in's rows, moved in time to end LEAD_IN_GAP_S before the run, then the run's; with segment ids (0 the
    lead-in's, 1 the run's: the estimator restarts between them, as at a new trip, keeping what it keeps of the car)."""
    ts = lead["timestamp_ms"].to_numpy()
    shift = int(run["timestamp_ms"][0].as_py()) - int(ts[-1]) - round(LEAD_IN_GAP_S * 1000.0)
    k = lead.column_names.index("timestamp_ms")
    lead = lead.set_column(k, lead.schema.field(k), pa.array(ts + shift))
    segments = np.repeat(np.array([0, 1], dtype=np.int64), [lead.num_rows, run.num_rows])
    return pa.concat_tables([lead, run]), segments


def estimates_on_runs(
    estimator, table: pa.Table, vehicles: dict, progress=None, lead_ins: pa.Table | None = None
) -> dict[str, np.ndarray]:
    """Run a (streaming-capable) estimator over every run of a simulated table, each from its start with the profile
    `vehicles` gives its run (the catalogue profile: catalogue_profile); the estimates joined with the truth, as arrays
    over the estimated samples. `lead_ins`: each run's lead-in (its run id + LEAD_IN_SUFFIX, presets.physics_lead_in),
    which the estimator reads first, unscored: a car that has driven before."""
    from roadgrip.sim.presets import LEAD_IN_SUFFIX

    parts = []
    runs = table["run_id"].unique().to_pylist()
    leads = dict(_runs(lead_ins)) if lead_ins is not None else {}
    for k, (run_id, run) in enumerate(_runs(table)):
        data, segments = run, np.zeros(run.num_rows, dtype=np.int64)
        if lead_ins is not None:
            data, segments = _after_lead_in(run, leads[f"{run_id}{LEAD_IN_SUFFIX}"])
        out = estimator.estimate_batch(data, segments, vehicles[run_id])
        ts = out["timestamp_ms"].to_numpy()
        keep = ts >= run["timestamp_ms"][0].as_py()
        rows = np.searchsorted(run["timestamp_ms"].to_numpy(), ts[keep])
        col = _truth_at(run, rows, vehicles[run_id], run_id)
        col |= {c: out[c].to_numpy(zero_copy_only=False)[keep] for c in ("mu_lower", "mu_upper", "excited")}
        col["mu_est"] = out["mu"].to_numpy()[keep]
        parts.append(col)
        if progress:
            progress(k + 1, len(runs))
    return {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def prior_estimates(table: pa.Table, vehicles: dict, baseline: PriorBaseline | None = None) -> dict[str, np.ndarray]:
    """The prior baseline on every sample of every run, in estimates_on_runs' form (never judged excited; the bound
    with the profile `vehicles` gives each run)."""
    baseline = baseline or prior_baseline()
    parts = []
    for run_id, run in _runs(table):
        n = run.num_rows
        col = _truth_at(run, np.arange(n), vehicles[run_id], run_id)
        col["mu_est"] = np.full(n, baseline.mu_median)
        col["mu_lower"] = np.full(n, baseline.mu_lower)
        col["mu_upper"] = np.full(n, baseline.mu_upper)
        col["excited"] = np.zeros(n, dtype=bool)
        parts.append(col)
    return {c: np.concatenate([p[c] for p in parts]) for c in parts[0]}


def estimator_bins(estimates: dict[str, np.ndarray], baseline_mu: float | None = None) -> list[dict]:
    """binned_metrics of estimates_on_runs' output (with the skill against a constant baseline_mu, if given)."""
    e = estimates
    bins = utilization_bin(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"], e["abs_active"])
    return binned_metrics(
        e["mu_est"], e["mu_lower"], e["mu_upper"], e["excited"], e["mu"], bins, e["bound"], baseline_mu
    )


BIN_ESTIMATORS = ("pmf", "ekf", "ukf", "default")


def run_bins_benchmark(seed: int = 0, estimators=BIN_ESTIMATORS, progress=None) -> list[dict]:
    """Every estimator (as `load_estimator` gives it: guarded) on the generalization benchmark's test runs (held-out
    vehicle and mu bands, every production-terminal effect on), by utilization bin, beside the prior baseline: one row
    per (estimator, bin), the prior's first. Each estimator gets the compact hatchback's catalogue profile (the test
    runs' vehicles are drawn around it), with the run's drive layout."""
    from roadgrip.estimators.learned import load_estimator
    from roadgrip.sim.presets import generalization_scenarios
    from roadgrip.sim.simulate import simulate
    from roadgrip.vehicle.params import COMPACT_HATCHBACK

    scenarios = generalization_scenarios("test", seed)
    table = simulate(scenarios)
    profiles = {s.run_id: catalogue_profile(COMPACT_HATCHBACK, s.vehicle) for s in scenarios}
    baseline = prior_baseline()
    rows = [
        {"estimator": PRIOR_NAME} | row for row in estimator_bins(prior_estimates(table, profiles), baseline.mu_median)
    ]
    for name in estimators:
        if progress:
            progress(f"{name} on {len(scenarios)} test runs by utilization bin")
        estimates = estimates_on_runs(load_estimator(name), table, profiles)
        rows += [{"estimator": name} | row for row in estimator_bins(estimates, baseline.mu_median)]
    return rows


def bins_markdown(rows: list[dict]) -> str:
    """The per-bin table: one line per estimator and bin; skill against the prior baseline where the rows have it."""
    lines = [
        "| estimator | bin | n | RMSE | skill | MAE | 90 % coverage | width | judged excited | below bound | negative |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        if r["n"] == 0:
            lines.append(f"| {r['estimator']} | {r['bin']} | 0 | - | - | - | - | - | - | - | - |")
            continue
        lines.append(
            f"| {r['estimator']} | {r['bin']} | {r['n']} | {r['rmse']:.3f} | {_signed(r.get('skill'))} | {r['mae']:.3f} | "
            f"{r['coverage']:.2f} | {r['width']:.2f} | {r['judged_excited']:.2f} | "
            f"{r['below_bound']:.3f} | {r['negative']} |"
        )
    return "\n".join(lines) + "\n"


def _signed(value) -> str:
    """A skill for a table: +0.41, or - where there is none."""
    return "-" if value is None or np.isnan(value) else f"{value:+.2f}"
