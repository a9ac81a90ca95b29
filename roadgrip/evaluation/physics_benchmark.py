"""The physics benchmark: can an estimator tell ice from dry asphalt on a production car, where the prior cannot?

Data (roadgrip/sim/presets.py: physics_benchmark_runs): mu over the whole range 0.1-1.2 (ice, snow, wet, dry), every
production-terminal effect on, manoeuvres that work the tires (braking into ABS, accelerating into traction control,
ramp and sine steering at 0.5-0.9 of the road's limit, low-speed tight turns) and cruising. Two splits with fixed seeds:
`validation` (paper SUV and compact hatchback, Dugoff and Magic Formula tires of 0.3-1.3 of the catalogue's stiffness)
is where constants may be chosen; `test` (midsize sedan, Burckhardt tire, whose surfaces carry their own slopes) is
looked at once per release of the numbers, never while choosing a constant.

Every estimator gets the catalogue profile of its car (bins.catalogue_profile), never the drawn one. Each table holds
the prior baseline (evaluation/baseline.py) first, then every estimator, by true utilization bin (bins.py) and by mu
band (<= 0.3, 0.3-0.6, >= 0.6), then by manoeuvre and mu band, each cell with RMSE, skill against the prior over the
same samples, and the coverage of the 90 % interval.

By channel set (`channels`, issue 26): the split simulated once with every optional channel on (CONTRACTS 3.1, the
error models of roadgrip/sim/channels.py), and once more with degraded GNSS where `gnss-degraded` is asked for
(ChannelModel.degraded_gnss: latency 0.2 s, 10 % outages, 5 % multipath outliers); each set blanks (nulls) the channels
it lacks, as a car that does not send them, so `base` is the benchmark without channels bit for bit. The prior once,
then every estimator under each set, its rows named `<estimator> [<set>]`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.evaluation.baseline import PRIOR_NAME, prior_baseline
from roadgrip.evaluation.bins import (
    BIN_ESTIMATORS,
    BIN_NAMES,
    binned_metrics,
    catalogue_profile,
    estimates_on_runs,
    prior_estimates,
    utilization_bin,
)

MU_BANDS = (("<= 0.3", 0.0, 0.3), ("0.3-0.6", 0.3, 0.6), (">= 0.6", 0.6, np.inf))
BAND_NAMES = tuple(name for name, _, _ in MU_BANDS)
ALL = "all"
_GNSS = ("gnss_speed_mps", "gnss_speed_accuracy_mps")
_FORCES = ("drive_force_n", "brake_force_n")
_STEERING = ("steering_torque_nm", "eps_assist_torque_nm")
CHANNEL_SETS = {
    "base": (),
    "gnss": _GNSS,
    "forces": _FORCES,
    "steering": _STEERING,
    "all": _GNSS + _FORCES + _STEERING,
    "gnss-degraded": _GNSS,
}


def blank_channels(table: pa.Table, keep: tuple[str, ...]) -> pa.Table:
    """The table with every optional channel not in `keep` null (not sent)."""
    from roadgrip.data.schema import CHANNEL_NAMES

    for name in CHANNEL_NAMES:
        if name in table.column_names and name not in keep:
            k = table.column_names.index(name)
            table = table.set_column(k, name, pa.nulls(table.num_rows, pa.float64()))
    return table


def mu_band(mu_true) -> np.ndarray:
    """The band name of each sample's true mu: <= 0.3, 0.3-0.6 (both ends open), >= 0.6."""
    mu = np.asarray(mu_true, dtype=np.float64)
    names = np.full(mu.shape, BAND_NAMES[1], dtype=object)
    names[mu <= MU_BANDS[0][2]] = BAND_NAMES[0]
    names[mu >= MU_BANDS[2][1]] = BAND_NAMES[2]
    return names


def cell_metrics(estimates: dict[str, np.ndarray], baseline_mu: float) -> list[dict]:
    """binned_metrics by utilization bin within each mu band (and over all bands): one row per (band, bin), with the
    skill against the constant baseline_mu over the cell's samples."""
    e = estimates
    bins = utilization_bin(e["ax_true_mps2"], e["ay_true_mps2"], e["mu"], e["abs_active"])
    bands = mu_band(e["mu"])
    rows = []
    for band in BAND_NAMES + (ALL,):
        m = np.ones(len(bands), dtype=bool) if band == ALL else bands == band
        cols = [e[c][m] for c in ("mu_est", "mu_lower", "mu_upper", "excited", "mu")]
        rows += [{"band": band} | r for r in binned_metrics(*cols, bins[m], e["bound"][m], baseline_mu)]
    return rows


def manoeuvre_metrics(estimates: dict[str, np.ndarray], manoeuvres: dict, baseline_mu: float) -> list[dict]:
    """cell_metrics over all utilizations within each manoeuvre (`manoeuvres`: run id -> manoeuvre): one row per
    (manoeuvre, band)."""
    of_sample = np.array([manoeuvres[r] for r in estimates["run_id"]], dtype=object)
    rows = []
    for name in dict.fromkeys(manoeuvres.values()):
        m = of_sample == name
        if m.any():
            part = {c: v[m] for c, v in estimates.items()}
            rows += [{"manoeuvre": name} | r for r in cell_metrics(part, baseline_mu) if r["bin"] == ALL]
    return rows


@dataclass(frozen=True)
class SimulatedSplit:
    """A physics split simulated: its drawn scenarios (presets.physics_benchmark_runs: (scenario, catalogue entry)),
    each run's catalogue profile by run id, and by channel set (None: no channels) the runs' table and their lead-ins'
    (None without a lead-in)."""

    drawn: list
    profiles: dict
    tables: dict

    @property
    def manoeuvres(self) -> dict:
        """Each run's manoeuvre by run id."""
        return {s.run_id: s.manoeuvre for s, _ in self.drawn}


def simulate_split(
    split: str = "validation",
    runs: int | None = None,
    channels: tuple[str, ...] | None = None,
    lead_in_s: float = 0.0,
    progress=None,
) -> SimulatedSplit:
    """A split's runs simulated once with every optional channel on where `channels` names sets (once more with
    degraded GNSS where `gnss-degraded` is among them), each set's tables with the channels it lacks blanked; without
    `channels`, the runs as the presets draw them (key None). `lead_in_s` > 0: each run's calm lead-in
    (presets.physics_lead_in) simulated beside it (module doc)."""
    import dataclasses

    from roadgrip.sim.channels import ChannelModel
    from roadgrip.sim.presets import LEAD_IN_SUFFIX, physics_benchmark_runs, physics_lead_in
    from roadgrip.sim.sensors import SensorModel
    from roadgrip.sim.simulate import simulate
    from roadgrip.validation import check_choice

    for name in channels or ():
        check_choice("physics benchmark", "channels", name, set(CHANNEL_SETS))
    drawn = physics_benchmark_runs(split, runs)
    (progress or (lambda message: None))(f"simulating the {len(drawn)} runs of the {split} split")
    scenarios = [s for s, _ in drawn]
    if channels:
        scenarios = [dataclasses.replace(s, effects=s.effects.with_channels()) for s in scenarios]
    leads = [physics_lead_in(s, lead_in_s) for s in scenarios] if lead_in_s > 0 else []

    def simulated(sensors=SensorModel()):
        both = simulate(scenarios + leads, sensors)
        is_lead = pc.ends_with(both["run_id"], LEAD_IN_SUFFIX)
        return both.filter(pc.invert(is_lead)), both.filter(is_lead) if leads else None

    table, lead_table = simulated()
    tables = {None: (table, lead_table)} if not channels else {}
    for name in channels or ():
        source = (table, lead_table)
        if name == "gnss-degraded":
            source = simulated(SensorModel(channels=ChannelModel.degraded_gnss()))
        tables[name] = tuple(None if t is None else blank_channels(t, CHANNEL_SETS[name]) for t in source)
    return SimulatedSplit(
        drawn,
        {s.run_id: catalogue_profile(entry, s.vehicle) for s, entry in drawn},
        tables,
    )


def run_physics_benchmark(
    split: str = "validation",
    estimators=BIN_ESTIMATORS,
    runs: int | None = None,
    progress=None,
    channels: tuple[str, ...] | None = None,
    lead_in_s: float = 0.0,
):
    """The prior baseline and every estimator (as `load_estimator` gives it: guarded) on a split's runs: one row per
    (estimator, band, bin) with manoeuvre 'all', then one per (estimator, manoeuvre, band) over all bins; the prior's
    first. `channels`: channel sets (CHANNEL_SETS) to run every estimator under (module doc); None: no channels.
    `lead_in_s`: every estimator first reads that long a calm drive of the same car (presets.physics_lead_in), a new
    trip before the run, its rows named `<estimator> calibrated` (module doc); 0: a car seen for the first time."""
    from roadgrip.estimators.learned import load_estimator

    say = progress or (lambda message: None)
    split_runs = simulate_split(split, runs, channels, lead_in_s, say)
    manoeuvres = split_runs.manoeuvres
    baseline_mu = prior_baseline().mu_median
    rows = []
    table = next(iter(split_runs.tables.values()))[0]
    runs_of = [(PRIOR_NAME, None, (table, None))] + [
        (e, c, t) for c, t in split_runs.tables.items() for e in estimators
    ]
    for name, channel_set, (data, lead_ins) in runs_of:
        label = name if channel_set is None else f"{name} [{channel_set}]"
        if lead_ins is not None:
            label += " calibrated"
        say(f"{label} on the {split} split")
        if name == PRIOR_NAME:
            estimates = prior_estimates(data, split_runs.profiles)
        else:
            estimates = estimates_on_runs(load_estimator(name), data, split_runs.profiles, lead_ins=lead_ins)
        rows += [{"estimator": label, "manoeuvre": ALL} | r for r in cell_metrics(estimates, baseline_mu)]
        rows += [{"estimator": label} | r for r in manoeuvre_metrics(estimates, manoeuvres, baseline_mu)]
    return rows


def rows_table(rows: list[dict]) -> pa.Table:
    """The rows as a table with every column any row has (an empty cell's row has only its names and n: nulls)."""
    columns = list(dict.fromkeys(k for r in rows for k in r))
    return pa.table({c: [r.get(c) for r in rows] for c in columns})


def _cell(row: dict | None) -> str:
    if row is None or row["n"] == 0:
        return "-"
    skill = "-" if np.isnan(row["skill"]) else f"{row['skill']:+.2f}"
    return f"{row['rmse']:.3f} / {skill} / {row['coverage']:.2f} ({row['n']})"


def physics_markdown(rows: list[dict]) -> str:
    """The table: one line per estimator and utilization bin, one column per mu band; each cell RMSE / skill against
    the prior / 90 % coverage (samples)."""
    found = {(r["estimator"], r.get("manoeuvre", ALL), r["band"], r["bin"]): r for r in rows}
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    manoeuvres = [m for m in dict.fromkeys(r.get("manoeuvre", ALL) for r in rows) if m != ALL]
    header = " | ".join(f"mu {b}" for b in BAND_NAMES) + " | all mu |"
    rule = "|---|---|" + "---|" * (len(BAND_NAMES) + 1)
    lines = ["Each cell: RMSE / skill (1 - RMSE / RMSE of the prior, same samples) / 90 % coverage (samples).", ""]
    lines += [f"| estimator | utilization | {header}", rule]
    for name in estimators:
        for b in BIN_NAMES + (ALL,):
            cells = " | ".join(_cell(found.get((name, ALL, band, b))) for band in BAND_NAMES + (ALL,))
            lines.append(f"| {name} | {b} | {cells} |")
    if manoeuvres:
        lines += ["", "By manoeuvre, every utilization:", "", f"| estimator | manoeuvre | {header}", rule]
        for name in estimators:
            for m in manoeuvres:
                cells = " | ".join(_cell(found.get((name, m, band, ALL))) for band in BAND_NAMES + (ALL,))
                lines.append(f"| {name} | {m} | {cells} |")
    return "\n".join(lines) + "\n"
