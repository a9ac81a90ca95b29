"""The real-vehicle benchmark (paper 5.2, Table 7; CONTRACTS 4 `real-vehicle`), reproduced in simulation.

The paper drove a 10 km expressway forward and reverse, twice each, in fine weather, accelerating and decelerating; its
vehicle-based system estimated the dry road's adhesion coefficient (0.576-0.628), and a single-wheel sideway-force test
vehicle measured the sideway force coefficient (SFC) of the same road wetted (0.408-0.431); the ratio of the means,
wet/dry, is about 0.70, against about 0.68 from Burckhardt's wet and dry asphalt. Here:

- Road: a 10 km expressway polyline (straights and arcs of 1000-2000 m radius, ALIGNMENT) whose adhesion coefficient is
  Burckhardt's dry asphalt (peak 1.170) dry and Burckhardt's wet asphalt (peak 0.801) wet, both times one texture factor
  1 + sum_k a_k sin(2 pi s / lambda_k + phi_k) of the station s (TEXTURE: +-6 % at most; the phases from the seed): the
  same pavement, so the same texture wet and dry. Reverse: the same road driven the other way (polyline and mu reversed,
  the wheel tracks swapped).
- Vehicle: the paper's SUV (PAPER_SUV) on Burckhardt dry-asphalt tires, four groups (first/second x forward/reverse),
  each with its own seed: its own accelerate-cruise-brake cycles (test_drive_profile) and sensor noise.
- Estimates: the EKF and the shipped learned model (load_estimator("ekf"), load_estimator("default")) on each group's
  telemetry, from LEAD_IN_M before the section (a straight approach: a terminal streams all the time, so the estimator
  has a past when the section begins); only the estimates on the section count. A group's value is the mean of the estimator's excited estimates on the test section (its own judgement,
  CONTRACTS 3.4), beside the mean of all its estimates and the mean over the samples that CONTRACTS 4's truth calls excited.
- Reference: the SCRIM-like test wheel of sideway_force.py over the wetted road in the group's direction.
- Outputs: metrics.csv (per group), table7.csv / table7.md (the paper's layout, our columns beside its), ratios.csv (wet/dry
  ratios of the means, with Burckhardt's), estimates.parquet, sfc.parquet and one figure.

Size: over 500 lines because the paper's Table 7: the expressway, the drives, the sideway-force test wheel and the
comparison, one experiment.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Callable
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
from matplotlib.figure import Figure

from roadgrip.estimators.excitation import excited as truth_excited
from roadgrip.estimators.learned import load_estimator
from roadgrip.evaluation.sideway_force import SfcSurvey, SidewayForceWheel, burckhardt_sfc
from roadgrip.sim.driver import DRIVER_ACCEL_LIMITS_MPS2, SpeedProfile
from roadgrip.sim.roads import MU_MAX, MuProfile, project_on_path
from roadgrip.sim.roads import Path as RoadPath
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import kmh_to_mps, mps_to_kmh
from roadgrip.vehicle.params import PAPER_SUV
from roadgrip.vehicle.tires import BurckhardtTire
from roadgrip.vehicle.tires.burckhardt import SURFACES, burckhardt_curve, peak_mu

ROAD_LENGTH_M = 10_000.0  # paper 5.2
POLYLINE_STEP_M = 5.0
MU_KNOT_SPACING_M = 25.0  # the mu profile is linear between knots; the shortest texture wavelength has 12 per period
# (share of the length, radius m (0: straight), +1 left / -1 right); radii of 1000 m and more, as for 120 km/h
ALIGNMENT = (
    (0.12, 0.0, 0),
    (0.08, 1500.0, 1),
    (0.15, 0.0, 0),
    (0.10, 1200.0, -1),
    (0.12, 0.0, 0),
    (0.07, 2000.0, 1),
    (0.14, 0.0, 0),
    (0.09, 1000.0, -1),
    (0.13, 0.0, 0),
)
TEXTURE = ((0.03, 2500.0), (0.02, 900.0), (0.01, 300.0))  # (amplitude, wavelength m) of the texture factor
DRY_SURFACE, WET_SURFACE = "dry_asphalt", "wet_asphalt"
GROUPS = ("first_forward", "second_forward", "first_reverse", "second_reverse")  # paper, Table 7
ESTIMATORS = ("ekf", "default")
ESTIMATOR_LABELS = {"default": "learned"}  # column prefix and name in the tables; others use their spec
DISPLAY_NAMES = {"ekf": "EKF", "ukf": "UKF"}  # in table7.md; others as their label

# The test drive: accelerate, cruise, brake, hold, repeated (test_drive_profile)
ENTRY_SPEED_MPS = kmh_to_mps(80.0)  # the car enters the test section at speed
TOP_SPEED_KMH = (100.0, 115.0)  # under the 120 km/h limit of China's expressways
LOW_SPEED_KMH = (55.0, 75.0)
ACCEL_MPS2 = (2.0, 3.0)  # firm, within the SUV's power at these speeds (250 kW: 4.3 m/s^2 at 30 m/s)
CRUISE_S = (4.0, 10.0)
HOLD_S = (1.0, 3.0)
FIRM_BRAKE_MPS2 = (5.5, 8.0)  # 0.56-0.82 g: utilization 0.48-0.70 on the 1.17 dry road
FULL_BRAKE_SHARE = 0.3  # share of the brakings that are full stops of the pedal (ABS), as in a brake test
FULL_BRAKE_MPS2 = -DRIVER_ACCEL_LIMITS_MPS2[0]  # the driver's full pedal, 1.2 g
LEAD_IN_M = 1000.0  # straight approach: the estimators run before the section, as a terminal streams all the time
SECTION_MARGIN_M = 150.0  # the profile runs past the section's end, so that the car completes it
RUN_OUT_M = 500.0  # straight road past the section's end


def _load_paper() -> dict[str, dict]:
    """The paper's Table 7: {test_group: {vehicle_based_estimate_dry, single_wheel_sfc_wet}}."""
    text = resources.files("roadgrip.evaluation").joinpath("reference/paper_real_vehicle.csv").read_text()
    rows = csv.DictReader(line for line in text.splitlines() if line.strip() and not line.startswith("#"))
    return {r["test_group"]: {k: float(v) for k, v in r.items() if k != "test_group"} for r in rows}


PAPER_TABLE7 = _load_paper()


# ------------------------------------------------------------------------------------------------------------- the road


def texture_factor(station_m, phases_rad) -> np.ndarray:
    """1 + sum_k a_k sin(2 pi s / lambda_k + phi_k) over TEXTURE: the pavement's mild variation along the road."""
    s = np.asarray(station_m, dtype=np.float64)
    return 1.0 + sum(a * np.sin(2.0 * math.pi * s / lam + phi) for (a, lam), phi in zip(TEXTURE, phases_rad))


def alignment_points(length_m: float) -> np.ndarray:
    """The expressway's polyline (m, east/north): ALIGNMENT's straights and arcs scaled to length_m, a point every
    POLYLINE_STEP_M (or closer on a short road)."""
    step = min(POLYLINE_STEP_M, length_m / 50.0)
    points, heading, here = [np.zeros(2)], 0.0, np.zeros(2)
    for share, radius, side in ALIGNMENT:
        n = max(math.ceil(share * length_m / step), 1)
        ds = share * length_m / n
        for _ in range(n):
            turn = side * ds / radius if radius > 0 else 0.0  # chords of length ds: the polyline is length_m long
            here = here + ds * np.array([math.cos(heading + turn / 2), math.sin(heading + turn / 2)])
            heading += turn
            points.append(here)
    return np.array(points)


def reverse_profile(mu: MuProfile, length_m: float) -> MuProfile:
    """The profile seen driving [0, length_m] the other way: station s becomes length_m - s, left and right swap."""
    s = mu.stations_m
    if s[0] != 0.0 or s[-1] > length_m:
        raise ValueError(f"reverse_profile needs stations in [0, length_m={length_m}] from 0, got {s.tolist()}")
    if mu.mode == "linear":
        if s[-1] != length_m:
            raise ValueError(f"a linear profile to reverse must end at length_m={length_m}, got {s[-1]}")
        return MuProfile(length_m - s[::-1], mu.mu_right[::-1], mu.mu_left[::-1], "linear")
    ends = np.append(s[1:], length_m)  # step: value k holds on [s_k, s_k+1), here on (L - s_k+1, L - s_k]
    return MuProfile(length_m - ends[::-1], mu.mu_right[::-1], mu.mu_left[::-1], "step")


@dataclass(frozen=True, eq=False)
class Expressway:
    """The test section: its polyline, and its adhesion coefficient dry and wet along it (stations in the direction
    driven)."""

    path: RoadPath
    mu_dry: MuProfile
    mu_wet: MuProfile
    direction: str = "forward"

    def __post_init__(self):
        length = float(self.mu_dry.stations_m[-1])
        if self.mu_wet.stations_m[-1] != length or abs(self.path.length_m - length) > 1e-6 * length:
            raise ValueError(
                f"Expressway path ({self.path.length_m} m), mu_dry ({length} m) and mu_wet "
                f"({self.mu_wet.stations_m[-1]} m) must span one length"
            )
        if self.direction not in ("forward", "reverse"):
            raise ValueError(f"Expressway.direction must be 'forward' or 'reverse', got {self.direction!r}")

    @property
    def length_m(self) -> float:
        """The section's length: the last knot of its mu profiles (the polyline's length to 1e-6)."""
        return float(self.mu_dry.stations_m[-1])

    def reversed(self) -> Expressway:
        other = "reverse" if self.direction == "forward" else "forward"
        return Expressway(
            RoadPath(self.path.points_m[::-1].copy()),
            reverse_profile(self.mu_dry, self.length_m),
            reverse_profile(self.mu_wet, self.length_m),
            other,
        )

    def route_mean(self, mu: MuProfile) -> float:
        """Mean over the section's length (both tracks) of a linear profile with knots at 0 and length_m: the exact
        integral by the trapezoid rule."""
        s, m = mu.stations_m, 0.5 * (mu.mu_left + mu.mu_right)
        return float(np.trapezoid(m, s) / (s[-1] - s[0]))

    def driven_path(self, lead_in_m: float, run_out_m: float) -> RoadPath:
        """The section with a straight approach of lead_in_m along its first heading and a straight run-out along its
        last."""
        p = self.path.points_m
        first = (p[1] - p[0]) / np.hypot(*(p[1] - p[0]))
        last = (p[-1] - p[-2]) / np.hypot(*(p[-1] - p[-2]))
        n = math.ceil(lead_in_m / POLYLINE_STEP_M)
        before = p[0] - np.outer(np.arange(n, 0, -1) * (lead_in_m / n), first) if n else np.empty((0, 2))
        after = p[-1] + np.outer(np.arange(1, math.ceil(run_out_m / POLYLINE_STEP_M) + 1) * POLYLINE_STEP_M, last)
        return RoadPath(np.vstack([before, p, after]))

    def driven_mu(self, lead_in_m: float) -> MuProfile:
        """The dry profile along the driven path: shifted by the approach, whose mu is the section's first value."""
        return MuProfile(
            self.mu_dry.stations_m + lead_in_m, self.mu_dry.mu_left, self.mu_dry.mu_right, self.mu_dry.mode
        )


def expressway(
    length_m: float = ROAD_LENGTH_M, rng: np.random.Generator | None = None, friction_scale: float = 1.0
) -> Expressway:
    """The forward test section. Dry: peak of Burckhardt's dry asphalt x texture x friction_scale; wet: the same with
    wet asphalt. friction_scale (1: the tabulated surfaces) moves the whole pavement up or down."""
    if not length_m >= 100.0:
        raise ValueError(f"expressway length_m must be >= 100, got {length_m!r}")
    top = peak_mu(*SURFACES[DRY_SURFACE]) * friction_scale * (1.0 + sum(a for a, _ in TEXTURE))
    if not (friction_scale > 0.0 and top <= MU_MAX):
        raise ValueError(f"expressway friction_scale must keep the dry mu in (0, {MU_MAX}], got {friction_scale!r}")
    rng = np.random.default_rng(0) if rng is None else rng
    phases = rng.uniform(0.0, 2.0 * math.pi, len(TEXTURE))
    knots = np.linspace(0.0, length_m, math.ceil(length_m / MU_KNOT_SPACING_M) + 1)
    texture = texture_factor(knots, phases) * friction_scale
    dry, wet = (peak_mu(*SURFACES[name]) * texture for name in (DRY_SURFACE, WET_SURFACE))
    path = RoadPath(alignment_points(length_m))
    return Expressway(path, MuProfile(knots, dry, dry, "linear"), MuProfile(knots, wet, wet, "linear"))


# -------------------------------------------------------------------------------------------------------- the test drive


def test_drive_profile(distance_m: float, rng: np.random.Generator) -> SpeedProfile:
    """Accelerate to a top speed, cruise, brake to a low speed (firmly, or now and then with the full pedal), hold;
    repeated until the reference has covered distance_m. Starts at ENTRY_SPEED_MPS, accelerating first."""
    times, speeds = [0.0], [ENTRY_SPEED_MPS]
    covered = 0.0
    while covered < distance_m:
        top = kmh_to_mps(rng.uniform(*TOP_SPEED_KMH))
        low = kmh_to_mps(rng.uniform(*LOW_SPEED_KMH))
        brake = FULL_BRAKE_MPS2 if rng.random() < FULL_BRAKE_SHARE else rng.uniform(*FIRM_BRAKE_MPS2)
        steps = (
            (abs(top - speeds[-1]) / rng.uniform(*ACCEL_MPS2), top),
            (rng.uniform(*CRUISE_S), top),
            ((top - low) / brake, low),
            (rng.uniform(*HOLD_S), low),
        )
        for dt, target in steps:
            covered += 0.5 * (speeds[-1] + target) * dt
            times.append(times[-1] + dt)
            speeds.append(target)
    return SpeedProfile(times, speeds)


def group_seeds(
    seed: int,
) -> tuple[np.random.Generator, dict[str, tuple[int, np.random.Generator, np.random.Generator]]]:
    """The road's generator, and per group (scenario seed, drive generator, test-wheel generator), from one seed."""
    road, *groups = np.random.SeedSequence(seed).spawn(1 + len(GROUPS))
    out = {}
    for name, child in zip(GROUPS, groups):
        drive, wheel = child.spawn(2)
        out[name] = (int(child.generate_state(1)[0]), np.random.default_rng(drive), np.random.default_rng(wheel))
    return np.random.default_rng(road), out


def group_scenarios(roads: dict[str, Expressway], seeds: dict) -> list[Scenario]:
    """One run per group, all of one duration (the longest profile's), so that they integrate as one batch."""
    profiles = {
        g: test_drive_profile(LEAD_IN_M + roads[_direction(g)].length_m + SECTION_MARGIN_M, seeds[g][1]) for g in GROUPS
    }
    duration = max(float(p.times_s[-1]) for p in profiles.values())
    scenarios = []
    for g in GROUPS:
        road, profile = roads[_direction(g)], profiles[g]
        run_out = RUN_OUT_M + (duration - profile.times_s[-1]) * profile.speeds_mps[-1]
        scenarios.append(
            Scenario(
                run_id=f"real-vehicle-{g}",
                path=road.driven_path(LEAD_IN_M, run_out),
                mu=road.driven_mu(LEAD_IN_M),
                speed=profile,
                condition="real-vehicle-dry",
                road=f"expressway-{road.direction}",
                vehicle=PAPER_SUV,
                tire=BurckhardtTire(DRY_SURFACE),
                duration_s=duration,
                seed=seeds[g][0],
                experiment=1 if g.startswith("first") else 2,
                manoeuvre="accelerate_decelerate",
            )
        )
    return scenarios


def _direction(group: str) -> str:
    return group.split("_")[1]


def stations_along(path: RoadPath, x_m, y_m) -> np.ndarray:
    """Station (m) of each position on the path, by projection (positions in driving order)."""
    table = path.table()
    seg, out = 0, np.empty(len(x_m))
    for i, (x, y) in enumerate(zip(x_m, y_m)):
        seg, out[i], _ = project_on_path(table, table.shape[0], seg, float(x), float(y))
    return out


# ------------------------------------------------------------------------------------------------------- the benchmark


def _label(spec: str) -> str:
    return ESTIMATOR_LABELS.get(spec, spec)


def _estimates_on_section(estimator, run: pa.Table, on_section: np.ndarray) -> dict[str, np.ndarray]:
    """The estimator over the whole run (from its start, one segment), its estimates on the section's samples: sample
    index, mu, excited."""
    est = estimator.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), PAPER_SUV)
    index = np.searchsorted(run["timestamp_ms"].to_numpy(), est["timestamp_ms"].to_numpy())
    keep = on_section[index]
    return {"index": index[keep], "mu": est["mu"].to_numpy()[keep], "excited": est["excited"].to_numpy()[keep]}


def _mean(values) -> float:
    values = np.asarray(values, dtype=np.float64)
    return float(values.mean()) if values.size else float("nan")


def run_real_vehicle_benchmark(
    out: str | Path,
    seed: int = 0,
    length_m: float | None = None,
    estimators=ESTIMATORS,
    friction_scale: float = 1.0,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict:
    """Simulate the four test groups, estimate, survey the wet road, write the outputs to `out`.

    length_m: the section's length (default ROAD_LENGTH_M; shorter for tests); estimators: specs for load_estimator
    ("default" is shown as "learned"); friction_scale: the pavement's level against Burckhardt's tabulated asphalt
    (expressway); progress(done, total, message). Returns {"metrics": rows, "ratios": rows, and a Path per written
    file}."""
    if not estimators:
        raise ValueError("run_real_vehicle_benchmark needs at least one estimator, got none")
    say = progress or (lambda done, total, message: None)
    total = 2 + len(GROUPS) * (1 + len(estimators))
    length_m = ROAD_LENGTH_M if length_m is None else float(length_m)
    road_rng, seeds = group_seeds(seed)
    forward = expressway(length_m, road_rng, friction_scale)
    roads = {"forward": forward, "reverse": forward.reversed()}
    say(0, total, f"simulating {len(GROUPS)} test groups over {length_m / 1000:g} km")
    scenarios = group_scenarios(roads, seeds)
    table = simulate(scenarios)
    done = 1
    loaded = {spec: load_estimator(spec) for spec in estimators}
    metrics, traces, surveys = [], [], {}
    for g, scenario in zip(GROUPS, scenarios):
        road = roads[_direction(g)]
        run = table.filter(pc.equal(table["run_id"], scenario.run_id))
        col = {
            c: run[c].to_numpy()
            for c in ("t_s", "x_m", "y_m", "vx_true_mps", "ax_true_mps2", "ay_true_mps2", "abs_active", "mu")
        }
        station = stations_along(scenario.path, col["x_m"], col["y_m"]) - LEAD_IN_M
        on_section = (station >= 0.0) & (station <= road.length_m)
        if station[-1] < road.length_m:
            raise RuntimeError(f"{g}: the car reached only {station[-1]:.0f} m of {road.length_m:.0f} m")
        exc_truth = truth_excited(col["ax_true_mps2"], col["ay_true_mps2"], col["abs_active"], col["mu"])
        row = {
            "test_group": g,
            "direction": road.direction,
            "experiment": scenario.experiment,
            "run_seed": scenario.seed,
            "samples": int(on_section.sum()),
            "section_time_s": float(np.ptp(col["t_s"][on_section])),
            "length_m": road.length_m,
            "mean_speed_kmh": float(mps_to_kmh(col["vx_true_mps"][on_section].mean())),
            "truly_excited_share": float(exc_truth[on_section].mean()),
            "abs_share": float(col["abs_active"][on_section].mean()),
        }
        for spec, estimator in loaded.items():
            say(done, total, f"{g}: estimating with {estimator.name}")
            e = _estimates_on_section(estimator, run, on_section)
            name = _label(spec)
            row |= {
                f"{name}_dry_excited_mean": _mean(e["mu"][e["excited"]]),
                f"{name}_dry_all_mean": _mean(e["mu"]),
                f"{name}_dry_truth_excited_mean": _mean(e["mu"][exc_truth[e["index"]]]),
                f"{name}_judged_excited": int(e["excited"].sum()),
                f"{name}_estimates": int(e["mu"].size),
            }
            traces.append(
                pa.table(
                    {
                        "test_group": [g] * e["mu"].size,
                        "estimator": [name] * e["mu"].size,
                        "t_s": col["t_s"][e["index"]],
                        "station_m": station[e["index"]],
                        "speed_kmh": mps_to_kmh(col["vx_true_mps"][e["index"]]),
                        "mu_true": col["mu"][e["index"]],
                        "mu": e["mu"],
                        "excited": e["excited"],
                        "truly_excited": exc_truth[e["index"]],
                        "abs_active": col["abs_active"][e["index"]],
                    }
                )
            )
            done += 1
        say(done, total, f"{g}: sideway-force survey of the wetted road")
        survey = SidewayForceWheel().survey(road.mu_wet, road.length_m, seeds[g][2])
        surveys[g] = survey
        row |= {
            "true_dry_mu_route": road.route_mean(road.mu_dry),
            "true_dry_mu_samples": float(col["mu"][on_section].mean()),
            "true_wet_mu_route": road.route_mean(road.mu_wet),
            "sfc_wet": survey.mean_sfc,
            "sfc_wet_model": float(survey.sfc_model.mean()),
            "sfc_reports": int(survey.station_m.size),
            **{f"paper_{k}": v for k, v in PAPER_TABLE7[g].items()},
        }
        metrics.append(row)
        done += 1
    say(done, total, "writing the tables and the figure")
    ratios = ratio_rows(metrics, [_label(s) for s in estimators])
    paths = write_real_vehicle_report(
        metrics, ratios, pa.concat_tables(traces), surveys, out, [_label(s) for s in estimators], friction_scale
    )
    say(total, total, "done")
    return {"metrics": metrics, "ratios": ratios, **paths}


# ------------------------------------------------------------------------------------------------------------- ratios


def burckhardt_ratios(slip_angle_rad: float | None = None) -> list[dict]:
    """Burckhardt's wet/dry asphalt ratio under several definitions (rows: source, definition, dry, wet, ratio)."""
    wheel = SidewayForceWheel() if slip_angle_rad is None else SidewayForceWheel(slip_angle_rad=slip_angle_rad)
    dry, wet = SURFACES[DRY_SURFACE], SURFACES[WET_SURFACE]
    s = math.sin(wheel.slip_angle_rad)
    deg = math.degrees(wheel.slip_angle_rad)
    rows = [
        (
            "peak mu wet / peak mu dry (the adhesion coefficients; the definition we take for the paper's 0.68)",
            peak_mu(*dry),
            peak_mu(*wet),
        ),
        ("mu at a locked wheel (s = 1), wet / dry", burckhardt_curve(*dry, 1.0), burckhardt_curve(*wet, 1.0)),
        (
            f"mu at the test wheel's slip s = sin({deg:g} deg) = {s:.3f}, wet / dry",
            burckhardt_curve(*dry, s),
            burckhardt_curve(*wet, s),
        ),
        (
            f"SFC of the wet road at {deg:g} deg / peak mu dry (what the truth row measures)",
            peak_mu(*dry),
            float(burckhardt_sfc(peak_mu(*wet), wheel.slip_angle_rad, WET_SURFACE)),
        ),
    ]
    return [{"source": "Burckhardt model", "definition": d, "dry": a, "wet": b, "ratio": b / a} for d, a, b in rows]


def ratio_rows(metrics: list[dict], estimators: list[str]) -> list[dict]:
    """The ratio wet/dry of the means over the groups: the paper's, ours per estimator (excited and all estimates), the
    truth's, and Burckhardt's."""

    def mean(key):
        return float(np.mean([r[key] for r in metrics]))

    sfc = mean("sfc_wet")
    rows = [
        {
            "source": "paper Table 7",
            "definition": "mean SFC / mean vehicle-based estimate",
            "dry": mean("paper_vehicle_based_estimate_dry"),
            "wet": mean("paper_single_wheel_sfc_wet"),
        }
    ]
    for name in estimators:
        shown = DISPLAY_NAMES.get(name, name)
        rows += [
            {
                "source": f"ours, {shown}",
                "definition": "mean SFC / mean of the excited estimates",
                "dry": mean(f"{name}_dry_excited_mean"),
                "wet": sfc,
            },
            {
                "source": f"ours, {shown}",
                "definition": "mean SFC / mean of all estimates",
                "dry": mean(f"{name}_dry_all_mean"),
                "wet": sfc,
            },
        ]
    rows += [
        {
            "source": "truth",
            "definition": "mean SFC / true dry mu (route mean)",
            "dry": mean("true_dry_mu_route"),
            "wet": sfc,
        },
        {
            "source": "truth",
            "definition": "true wet mu / true dry mu (route means, peaks)",
            "dry": mean("true_dry_mu_route"),
            "wet": mean("true_wet_mu_route"),
        },
    ]
    for r in rows:
        r["ratio"] = r["wet"] / r["dry"] if r["dry"] > 0 else float("nan")
    return rows + burckhardt_ratios()


# ------------------------------------------------------------------------------------------------------------- outputs


def _f(value, digits=3) -> str:
    return "-" if value is None or not math.isfinite(value) else f"{value:.{digits}f}"


def table7_rows(metrics: list[dict], estimators: list[str]) -> list[dict]:
    """The paper's layout: per group (and their mean) the paper's two columns, then ours."""
    rows = []
    for r in metrics:
        rows.append(
            {
                "test_group": r["test_group"],
                "paper_vehicle_based_estimate_dry": r["paper_vehicle_based_estimate_dry"],
                "paper_single_wheel_sfc_wet": r["paper_single_wheel_sfc_wet"],
                **{f"ours_{n}_dry": r[f"{n}_dry_excited_mean"] for n in estimators},
                "true_dry_mu": r["true_dry_mu_route"],
                "ours_sfc_wet": r["sfc_wet"],
            }
        )
    mean = {k: float(np.mean([r[k] for r in rows])) for k in rows[0] if k != "test_group"}
    # ratio wet/dry of the means: each dry column against the SFC of its own source (the paper's, or our test wheel's)
    ratio = {
        k: (mean["paper_single_wheel_sfc_wet"] if k.startswith("paper") else mean["ours_sfc_wet"]) / v
        if "dry" in k
        else float("nan")
        for k, v in mean.items()
    }
    return rows + [{"test_group": "mean", **mean}, {"test_group": "ratio_wet_dry", **ratio}]


def table7_markdown(metrics: list[dict], ratios: list[dict], estimators: list[str], friction_scale: float) -> str:
    t7 = table7_rows(metrics, estimators)
    m0 = metrics[0]
    scale = "" if friction_scale == 1.0 else f" x {friction_scale:g} (friction_scale)"
    lines = [
        "# Real-vehicle test (paper Table 7), in simulation",
        "",
        (
            f"Road: {m0['length_m'] / 1000:g} km expressway (radii 1000-2000 m), dry: Burckhardt dry asphalt{scale} with a "
            f"texture variation of +-6 % (route mean {m0['true_dry_mu_route']:.3f}); wet: Burckhardt wet asphalt{scale}, "
            f"same texture (route mean {m0['true_wet_mu_route']:.3f}). Vehicle: the paper's SUV on Burckhardt dry-asphalt "
            "tires, accelerating (2-3 m/s^2) and braking (5.5-8 m/s^2, or the full pedal with ABS in 30 % of the brakings) "
            "between 55-75 and 100-115 km/h. Our dry columns: mean of each estimator's excited estimates over the section "
            "(EKF: roadgrip's extended Kalman filter; learned: the shipped default model). "
            "SFC: a simulated SCRIM-like test wheel (20 deg, 50 km/h, 2 kN, Burckhardt wet asphalt), mean of its 10 m "
            "values."
        ),
        "",
        "| Test group | paper: vehicle-based system (dry) | paper: single-wheel transverse force test vehicle (wet SFC) | "
        + " | ".join(f"ours: {DISPLAY_NAMES.get(n, n)} (dry)" for n in estimators)
        + " | true dry mu (route mean) | ours: simulated SFC (wet) |",
        "| :--- | ---: | ---: | " + "---: | " * len(estimators) + "---: | ---: |",
    ]
    for r in t7:
        name = (
            "Ratio wet/dry of the means"
            if r["test_group"] == "ratio_wet_dry"
            else r["test_group"].replace("_", " ").capitalize()
        )
        lines.append(f"| {name} | " + " | ".join(_f(v) for k, v in r.items() if k != "test_group") + " |")
    lines += [
        "",
        "## Ratio wet/dry of the means",
        "",
        "| source | definition | dry | wet | ratio wet/dry |",
        "| :--- | :--- | ---: | ---: | ---: |",
    ]
    lines += [
        f"| {r['source']} | {r['definition']} | {_f(r['dry'])} | {_f(r['wet'])} | {_f(r['ratio'], 3)} |" for r in ratios
    ]
    lines += [
        "",
        "## Per group",
        "",
        "| group | samples | mean speed km/h | truly excited | ABS | "
        + " | ".join(f"{n}: excited / all estimates | {n}: mean all | {n}: mean truly excited" for n in estimators)
        + " | SFC model (noiseless) |",
        "| :--- | " + "---: | " * (4 + 3 * len(estimators)) + "---: |",
    ]
    for r in metrics:
        cells = [
            r["test_group"],
            str(r["samples"]),
            f"{r['mean_speed_kmh']:.0f}",
            f"{r['truly_excited_share']:.1%}",
            f"{r['abs_share']:.1%}",
        ]
        for n in estimators:
            cells += [
                f"{r[f'{n}_judged_excited']} / {r[f'{n}_estimates']}",
                _f(r[f"{n}_dry_all_mean"]),
                _f(r[f"{n}_dry_truth_excited_mean"]),
            ]
        lines.append("| " + " | ".join(cells + [_f(r["sfc_wet_model"])]) + " |")
    return "\n".join(lines) + "\n"


def _write_csv(rows: list[dict], path: Path) -> Path:
    with path.open("w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(
            {k: (("" if math.isnan(v) else f"{v:.6g}") if isinstance(v, float) else v) for k, v in r.items()}
            for r in rows
        )
    return path


def plot_group(traces: pa.Table, survey: SfcSurvey, group: str, estimators: list[str], path: Path) -> Path:
    """Speed, the dry road's mu with the estimates, and the wet road's SFC along the route of one group."""
    rows = traces.filter(pc.equal(traces["test_group"], group))
    fig = Figure(figsize=(11, 8.5), layout="constrained")
    ax_v, ax_dry, ax_wet = fig.subplots(3, 1, sharex=True, height_ratios=(1, 2, 1.5))
    first = rows.filter(pc.equal(rows["estimator"], estimators[0]))
    km = first["station_m"].to_numpy() / 1000.0
    ax_v.plot(km, first["speed_kmh"].to_numpy(), color="0.3", lw=0.8)
    ax_v.set_ylabel("speed [km/h]")
    ax_dry.plot(km, first["mu_true"].to_numpy(), color="k", lw=1.6, label="true dry mu")
    for name, colour in zip(estimators, ("tab:blue", "tab:orange", "tab:green", "tab:red")):
        own = rows.filter(pc.equal(rows["estimator"], name))
        x, mu, exc = own["station_m"].to_numpy() / 1000.0, own["mu"].to_numpy(), own["excited"].to_numpy()
        ax_dry.plot(x, mu, color=colour, lw=0.6, alpha=0.6, label=f"{name}: all estimates")
        ax_dry.scatter(x[exc], mu[exc], s=7, color=colour, label=f"{name}: excited ({exc.sum()})", zorder=3)
        if exc.any():
            ax_dry.axhline(
                mu[exc].mean(), color=colour, ls="--", lw=1.0, label=f"{name}: excited mean {mu[exc].mean():.3f}"
            )
    ax_dry.set_ylabel("dry road: adhesion coefficient mu")
    ax_dry.legend(loc="lower right", fontsize=7, ncol=2)
    ax_wet.plot(survey.station_m / 1000.0, survey.sfc, color="tab:cyan", lw=0.7, label="SFC, 10 m values")
    ax_wet.plot(survey.station_m / 1000.0, survey.sfc_model, color="tab:purple", lw=1.2, label="SFC model (noiseless)")
    ax_wet.axhline(survey.mean_sfc, color="tab:cyan", ls="--", lw=1.0, label=f"SFC mean {survey.mean_sfc:.3f}")
    ax_wet.set_ylabel("wet road: SFC")
    ax_wet.set_xlabel(f"distance along the route, {group.replace('_', ' ')} [km]")
    ax_wet.legend(loc="lower right", fontsize=7, ncol=3)
    for ax in (ax_v, ax_dry, ax_wet):
        ax.grid(alpha=0.3)
    fig.suptitle(f"Real-vehicle test in simulation, {group.replace('_', ' ')}: dry-road estimates and wet-road SFC")
    fig.savefig(path, dpi=100)
    return path


def write_real_vehicle_report(
    metrics,
    ratios,
    traces: pa.Table,
    surveys: dict[str, SfcSurvey],
    out,
    estimators: list[str],
    friction_scale: float = 1.0,
) -> dict:
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "metrics_csv": _write_csv(metrics, out / "metrics.csv"),
        "table7_csv": _write_csv(table7_rows(metrics, estimators), out / "table7.csv"),
        "ratios_csv": _write_csv(ratios, out / "ratios.csv"),
    }
    paths["table7_md"] = out / "table7.md"
    paths["table7_md"].write_text(table7_markdown(metrics, ratios, estimators, friction_scale))
    pq.write_table(traces, out / "estimates.parquet")
    paths["estimates"] = out / "estimates.parquet"
    pq.write_table(
        pa.concat_tables(
            [
                pa.table(
                    {
                        "test_group": [g] * s.station_m.size,
                        "station_m": s.station_m,
                        "sfc": s.sfc,
                        "sfc_left": s.sfc_left,
                        "sfc_right": s.sfc_right,
                        "sfc_model": s.sfc_model,
                        "fy_n": s.fy_n,
                    }
                )
                for g, s in surveys.items()
            ]
        ),
        out / "sfc.parquet",
    )
    paths["sfc"] = out / "sfc.parquet"
    group = GROUPS[0]
    paths["figures"] = [plot_group(traces, surveys[group], group, estimators, out / f"real_vehicle_{group}.png")]
    return paths
