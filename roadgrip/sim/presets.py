"""Scenario presets: `paper` (the paper's CarSim data set, CONTRACTS 3.3) and `random` (for generalization).

Both are pure functions of a seed: the same seed gives the same scenarios, and the run seeds that drive the sensor noise are
spawned from it with numpy's SeedSequence.

Production-terminal realism (roadgrip/sim/production.py) is off in `paper` (the paper's CarSim-like setting) and on in
`random` and the generalization presets (`RANDOM_EFFECTS`): their runs get speed from the wheel speeds, accelerometer
mounting, bias and pitch, per-wheel rolling radii, CAN resolution, time offsets, a road grade and a tire stiffness factor.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MU_MAX, GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.units import G_MPS2, kmh_to_mps
from roadgrip.validation import check_choice
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV, TireParams, VehicleParams
from roadgrip.vehicle.tires import BurckhardtTire, DugoffTire, MagicFormulaTire, TireModel
from roadgrip.vehicle.tires.base import STIFFNESS_SCALE_BOUNDS

PAPER_DURATION_S = 40.0
PAPER_TOP_SPEED_MPS = kmh_to_mps(120.0)
PAPER_CIRCLE_RADIUS_M = 1000.0  # the paper gives none; 120 km/h on it asks 0.11 g, inside even the 0.2 road's limit
PAPER_SECTIONS_SPAN = 0.75  # share of the profile's distance that the four sections of a varying road cover
PAPER_CONDITIONS = {
    "low": [0.2],
    "medium": [0.5],
    "high": [0.8],
    "increasing": [0.1, 0.3, 0.6, 0.9],
    "decreasing": [0.9, 0.6, 0.3, 0.1],
}
PAPER_ROADS = ("straight", "circular")
RANDOM_MANOEUVRES = (
    "acceleration",
    "braking_abs",
    "braking_no_abs",
    "lane_change",
    "steady_curve",
    "sine_steer",
    "cruise",
)
PRESETS = (
    "paper",
    "random",
    "generalization-train",
    "generalization-calibration",
    "generalization-test",
    "physics-validation",
    "physics-test",
)
TRAINING_VEHICLES = (PAPER_SUV, MIDSIZE_SEDAN)  # the random preset's vehicles; the compact hatchback is held out
TYPICAL_WHEELBASE_M = 2.9  # to size steering inputs before the vehicle is drawn
RANDOM_EFFECTS = ProductionEffects.production()  # the random and generalization presets' production-terminal effects


def _road(kind: str, length_m: float, radius_m: float = PAPER_CIRCLE_RADIUS_M) -> Path:
    return Path.straight(length_m) if kind == "straight" else Path.circle(radius_m, length_m)


def _run_seeds(seed: int, n: int) -> list[int]:
    return [int(s.generate_state(1)[0]) for s in np.random.SeedSequence(seed).spawn(n)]


def paper_scenarios(seed: int = 0) -> list[Scenario]:
    """The paper's 20 runs: 5 conditions x 2 roads x 2 experiments, 0 - 120 - 0 km/h in 40 s, the Table 1 vehicle.

    The four mu sections of the increasing and decreasing roads are equal 125 m lengths that cover the first 500 m of the
    667 m the speed profile asks for: on a 0.1 section the car cannot accelerate or brake as asked and falls behind, and
    the margin lets it still reach the last section. The two experiments of a case differ by their seed: sensor noise and
    biases."""
    speed = SpeedProfile.accelerate_decelerate(PAPER_TOP_SPEED_MPS, PAPER_DURATION_S / 2, PAPER_DURATION_S)
    distance_m = speed.distance_m(PAPER_DURATION_S)
    cases = [(c, r, e) for c in PAPER_CONDITIONS for r in PAPER_ROADS for e in (1, 2)]
    scenarios = []
    for (condition, road, experiment), run_seed in zip(cases, _run_seeds(seed, len(cases))):
        values = PAPER_CONDITIONS[condition]
        scenarios.append(
            Scenario(
                run_id=f"paper-{condition}-{road}-e{experiment}",
                path=_road(road, 1.5 * distance_m + 300.0),
                mu=MuProfile.sections(values, PAPER_SECTIONS_SPAN * distance_m / len(values)),
                speed=speed,
                condition=condition,
                road=road,
                vehicle=PAPER_SUV,
                tire=DugoffTire(),
                duration_s=PAPER_DURATION_S,
                seed=run_seed,
                experiment=experiment,
                manoeuvre="accelerate_decelerate",
            )
        )
    return scenarios


def random_vehicle(rng: np.random.Generator, name: str, bases=TRAINING_VEHICLES) -> VehicleParams:
    """A vehicle drawn around one of `bases` (ranges in docs/VEHICLES.md)."""
    base = bases[int(rng.integers(len(bases)))]
    mass_scale = rng.uniform(0.85, 1.15)
    wheelbase = base.wheelbase_m * rng.uniform(0.95, 1.05)
    drive = str(rng.choice(["fwd", "rwd", "awd"]))
    return base.replace(
        name=name,
        mass_kg=base.mass_kg * mass_scale,
        yaw_inertia_kgm2=base.yaw_inertia_kgm2 * mass_scale,
        roll_inertia_kgm2=base.roll_inertia_kgm2 * mass_scale,
        wheelbase_m=wheelbase,
        cg_to_front_axle_m=wheelbase * rng.uniform(0.40, 0.55),
        cg_height_m=base.cg_height_m * rng.uniform(0.9, 1.1),
        wheel_radius_m=base.wheel_radius_m * rng.uniform(0.95, 1.05),
        drive=drive,
        front_drive_share={"fwd": 1.0, "rwd": 0.0, "awd": rng.uniform(0.3, 0.6)}[drive],
        tire_front=_scaled_tire(base.tire_front, rng.uniform(0.8, 1.2)),
        tire_rear=_scaled_tire(base.tire_rear, rng.uniform(0.8, 1.2)),
    )


def _scaled_tire(tire: TireParams, scale: float) -> TireParams:
    return TireParams(tire.longitudinal_stiffness_per_load * scale, tire.cornering_stiffness_per_load_per_rad * scale)


def draw_mu(rng: np.random.Generator, bands, n: int) -> np.ndarray:
    """n values uniform over the union of the bands [(lo, hi), ...]."""
    bands = np.asarray(bands, dtype=np.float64)
    widths = bands[:, 1] - bands[:, 0]
    if bands.ndim != 2 or bands.shape[1] != 2 or (widths <= 0).any() or bands.min() < 0.0 or bands.max() > MU_MAX:
        raise ValueError(f"mu bands must be (low, high) pairs with 0 <= low < high <= {MU_MAX}, got {bands.tolist()}")
    u = rng.uniform(0.0, widths.sum(), n)
    edges = np.cumsum(widths)
    k = np.minimum(np.searchsorted(edges, u, side="right"), len(bands) - 1)
    return bands[k, 0] + u - (edges[k] - widths[k])


def random_mu(
    rng: np.random.Generator, bands=((0.1, 1.0),), ramps: bool = True
) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    """1 to 5 sections of mu drawn from the bands, with steps (or ramps), sometimes split between the wheel tracks
    (the other track's mu drawn from the bands too). With ramps the mu between two sections passes through the gaps
    between bands: a benchmark that holds bands out asks for steps only.

    Returns (section starts as fractions of the run's distance, mu left, mu right, interpolation mode)."""
    n = int(rng.integers(1, 6))
    left = draw_mu(rng, bands, n)
    right = left.copy()
    if rng.random() < 0.15:
        right = draw_mu(rng, bands, n)
    starts = np.sort(rng.uniform(0.0, 1.0, n))
    starts[0] = 0.0
    starts = np.maximum.accumulate(starts + 1e-4 * np.arange(n))
    mode = str(rng.choice(["step", "linear"]))
    return starts, left, right, mode if ramps else "step"


def random_manoeuvre(rng: np.random.Generator, manoeuvre: str, duration_s: float, mu_min: float):
    """(speed profile, path builder, steer input, abs enabled) of one manoeuvre.

    Curves ask a lateral acceleration of up to 1.0 mu_min g and sine steering up to 0.7 mu_min g (mu_min: the lowest mu of the run's road), so that
    some runs reach the limit and slide while most stay below it, as drivers who know the road would."""
    steer = None
    abs_enabled = manoeuvre != "braking_no_abs"
    if manoeuvre == "acceleration":
        v0, v1, accel = rng.uniform(0.0, 10.0), rng.uniform(20.0, 40.0), rng.uniform(1.5, 5.0)
        speed = SpeedProfile([0.0, (v1 - v0) / accel, duration_s], [v0, v1, v1])
    elif manoeuvre in ("braking_abs", "braking_no_abs"):
        speed = _braking_cycles(rng, duration_s)
    elif manoeuvre == "sine_steer":
        v = rng.uniform(15.0, 30.0)
        speed = SpeedProfile([0.0, duration_s], [v, v])
        lateral_mps2 = rng.uniform(0.2, 0.7) * mu_min * G_MPS2
        amplitude = min(max(TYPICAL_WHEELBASE_M * lateral_mps2 / v**2, 0.005), 0.1)  # neutral-steer delta = L a_y / v^2
        steer = SteerInput(5.0, duration_s - 5.0, amplitude, rng.uniform(0.2, 1.0), 0.0)
    elif manoeuvre == "cruise":
        times = np.arange(0.0, duration_s, 10.0)
        speeds = np.clip(rng.uniform(15.0, 33.0) + rng.normal(0.0, 2.0, times.size), 5.0, 40.0)
        speed = SpeedProfile(np.append(times, duration_s), np.append(speeds, speeds[-1]), np.ones(times.size + 1, bool))
    elif manoeuvre == "steady_curve":
        radius = rng.uniform(60.0, 400.0)
        v_end = math.sqrt(rng.uniform(0.4, 1.0) * mu_min * G_MPS2 * radius)
        speed = SpeedProfile([0.0, duration_s], [min(rng.uniform(5.0, 10.0), v_end), min(v_end, 40.0)])
        return speed, (lambda length: Path.circle(radius, length)), None, True
    else:  # lane_change
        v = rng.uniform(15.0, 33.0)
        speed = SpeedProfile([0.0, duration_s], [v, v])
        spacing = rng.uniform(60.0, 150.0)
        transition = rng.uniform(30.0, 60.0)

        def lane_path(length):
            starts = np.arange(spacing, length - transition, spacing + transition)
            offsets = 3.5 * (np.arange(starts.size) % 2 == 0)
            return Path.lane_changes(length, starts, offsets, transition)

        return speed, lane_path, None, True
    return speed, Path.straight, steer, abs_enabled


def _braking_cycles(rng: np.random.Generator, duration_s: float) -> SpeedProfile:
    """Cruise, brake hard to a stop, wait, accelerate back; repeated over the run."""
    v = rng.uniform(15.0, 35.0)
    times, speeds = [0.0], [v]
    t = 0.0
    while True:
        cruise, decel, wait, accel = rng.uniform(3.0, 8.0), rng.uniform(4.0, 12.0), rng.uniform(1.0, 3.0), 2.5
        steps = [(cruise, v), (v / decel, 0.0), (wait, 0.0), (v / accel, v)]
        for dt, target in steps:
            t += dt
            if t >= duration_s:
                times.append(duration_s)
                speeds.append(float(np.interp(duration_s, [times[-1], t], [speeds[-1], target])))
                return SpeedProfile(times, speeds)
            times.append(t)
            speeds.append(target)


def random_grade(rng: np.random.Generator, grade_max_rad: float, distance_m: float) -> GradeProfile:
    """1 to 3 grades uniform in +-grade_max_rad at stations spread over the run's distance, linear between them (crests
    and sags as vertical curves)."""
    n = int(rng.integers(1, 4))
    stations = np.sort(rng.uniform(0.0, 1.0, n)) * distance_m
    stations[0] = 0.0
    stations = np.maximum.accumulate(stations + 1e-3 * np.arange(n))
    return GradeProfile(stations, rng.uniform(-grade_max_rad, grade_max_rad, n))


def random_scenarios(
    runs: int = 100,
    seed: int = 0,
    duration_s: float = PAPER_DURATION_S,
    mu_bands=((0.1, 1.0),),
    vehicles=TRAINING_VEHICLES,
    prefix: str = "random",
    ramps: bool = True,
    effects: ProductionEffects = RANDOM_EFFECTS,
) -> list[Scenario]:
    """Randomized vehicles (around `vehicles`), tire models, mu profiles (from `mu_bands`) and manoeuvres (see
    docs/SIMULATOR.md for the ranges), with the production-terminal `effects` (RANDOM_EFFECTS: all on;
    ProductionEffects.off() gives the runs of before they existed). The grade and the tire stiffness factor are drawn
    here, after everything else of a run, and only when their effect is on."""
    if runs < 1:
        raise ValueError(f"random preset runs must be >= 1, got {runs!r}")
    scenarios = []
    tires = (DugoffTire(), MagicFormulaTire(), BurckhardtTire())
    for k, run_seed in enumerate(_run_seeds(seed, runs)):
        rng = np.random.default_rng(run_seed)
        manoeuvre = RANDOM_MANOEUVRES[int(rng.integers(len(RANDOM_MANOEUVRES)))]
        starts, mu_left, mu_right, mu_mode = random_mu(rng, mu_bands, ramps)
        speed, build_path, steer, abs_enabled = random_manoeuvre(
            rng, manoeuvre, duration_s, float(min(mu_left.min(), mu_right.min()))
        )
        distance_m = speed.distance_m(duration_s)
        path = build_path(1.3 * distance_m + 300.0)
        vehicle = random_vehicle(rng, f"{prefix}-{k:05d}", vehicles)
        tire = tires[int(rng.integers(len(tires)))]
        grade = GradeProfile.flat()
        if effects.grade_max_rad:
            grade = random_grade(rng, effects.grade_max_rad, distance_m)
        if effects.tire_stiffness_spread:
            spread = effects.tire_stiffness_spread
            tire = dataclasses.replace(tire, stiffness_scale=float(rng.uniform(1.0 - spread, 1.0 + spread)))
        scenarios.append(
            Scenario(
                run_id=f"{prefix}-{k:05d}",
                path=path,
                mu=MuProfile(starts * distance_m, mu_left, mu_right, mu_mode),
                speed=speed,
                condition="random",
                road="curve" if manoeuvre == "steady_curve" else "straight",
                vehicle=vehicle,
                tire=tire,
                steer=steer,
                duration_s=duration_s,
                abs_enabled=abs_enabled,
                seed=run_seed,
                manoeuvre=manoeuvre,
                grade=grade,
                # half the fleet (every second run) sends the optional channels, where production effects are on
                effects=effects.with_channels() if k % 2 and effects.any_sensor_effect else effects,
            )
        )
    return scenarios


GENERALIZATION_TRAIN_MU_BANDS = ((0.1, 0.45), (0.55, 0.85))
GENERALIZATION_TEST_MU_BANDS = ((0.45, 0.55), (0.85, 1.0))
GENERALIZATION_RUNS = {"train": 160, "calibration": 40, "test": 40}


def generalization_scenarios(
    part: str, seed: int = 0, runs: int | None = None, effects: ProductionEffects = RANDOM_EFFECTS
) -> list[Scenario]:
    """The generalization benchmark's data (CONTRACTS 4): `train` and `calibration` runs on the sedan and the SUV with mu in
    GENERALIZATION_TRAIN_MU_BANDS; `test` runs on the held-out compact hatchback with mu only in the held-out bands.
    Steps only: ramps would pass through the held-out bands."""
    check_choice("generalization", "part", part, set(GENERALIZATION_RUNS))
    n = GENERALIZATION_RUNS[part] if runs is None else runs
    offset = {"train": 0, "calibration": 1, "test": 2}[part]
    if part == "test":
        return random_scenarios(
            n,
            seed + offset,
            mu_bands=GENERALIZATION_TEST_MU_BANDS,
            vehicles=(COMPACT_HATCHBACK,),
            prefix=part,
            ramps=False,
            effects=effects,
        )
    return random_scenarios(
        n,
        seed + offset,
        mu_bands=GENERALIZATION_TRAIN_MU_BANDS,
        vehicles=TRAINING_VEHICLES,
        prefix=part,
        ramps=False,
        effects=effects,
    )


def preset_scenarios(preset: str, runs: int | None = None, seed: int = 0) -> list[Scenario]:
    check_choice("simulate", "preset", preset, set(PRESETS))
    if preset == "paper":
        if runs is not None and runs != 20:
            raise ValueError(
                f"the paper preset has exactly 20 runs (5 conditions x 2 roads x 2 experiments), got runs={runs}"
            )
        return paper_scenarios(seed)
    if preset.startswith("generalization-"):
        return generalization_scenarios(preset.removeprefix("generalization-"), seed, runs)
    if preset.startswith("physics-"):
        if seed != 0:
            raise ValueError(f"the physics presets' seeds are fixed per split (PHYSICS_SPLITS), got seed={seed}")
        return [s for s, _ in physics_benchmark_runs(preset.removeprefix("physics-"), runs)]
    return random_scenarios(100 if runs is None else runs, seed)


# The physics benchmark (roadgrip/evaluation/physics_benchmark.py): mu over the whole range, the manoeuvres that excite
# the tires, every production effect on; a validation split for choosing constants and a test split on a vehicle and a
# tire model that no choice of constant looked at. The splits' seeds are fixed: the numbers are the same on every machine.
PHYSICS_SURFACES = {"ice": (0.1, 0.2), "snow": (0.2, 0.4), "wet": (0.4, 0.7), "dry": (0.7, 1.2)}
PHYSICS_MANOEUVRES = ("braking_abs", "acceleration", "ramp_steer", "sine_steer", "cruise", "tight_turn")
PHYSICS_UTILIZATION = (0.5, 0.9)  # share of mu g the steering manoeuvres and the tight turns ask for
PHYSICS_LIMIT_UTILIZATION = (0.7, 1.4)  # share of mu g braking and accelerating ask for: most reach ABS or TCS
PHYSICS_DURATION_S = 30.0
PHYSICS_TIGHT_RADIUS_M = (10.0, 25.0)  # junction turns and roundabouts
ROUNDABOUT_ARC_RAD = 1.5 * math.pi  # entering right, leaving by the third exit: three quarters around (left)
ROUNDABOUT_GAP_M = 30.0  # straight road between one roundabout's exit and the next one's entry


def roundabouts(radius_m: float, length_m: float, segment_m: float = 2.0) -> Path:
    """A road through roundabouts of the given radius, one after another: ROUNDABOUT_GAP_M straight, three quarters of
    a circle to the left (driving on the right), ROUNDABOUT_GAP_M straight, and so on until length_m."""
    heading, x, y = 0.0, 0.0, 0.0
    points = [(x, y)]
    travelled = 0.0
    while travelled < length_m:
        x, y = x + ROUNDABOUT_GAP_M * math.cos(heading), y + ROUNDABOUT_GAP_M * math.sin(heading)
        points.append((x, y))
        n = max(math.ceil(ROUNDABOUT_ARC_RAD * radius_m / segment_m), 2)
        cx, cy = x - radius_m * math.sin(heading), y + radius_m * math.cos(heading)  # centre on the left
        for theta in np.linspace(0.0, ROUNDABOUT_ARC_RAD, n + 1)[1:]:
            a = heading - math.pi / 2 + theta
            points.append((cx + radius_m * math.cos(a), cy + radius_m * math.sin(a)))
        heading += ROUNDABOUT_ARC_RAD
        x, y = points[-1]
        travelled += ROUNDABOUT_GAP_M + ROUNDABOUT_ARC_RAD * radius_m
    points.append((x + ROUNDABOUT_GAP_M * math.cos(heading), y + ROUNDABOUT_GAP_M * math.sin(heading)))
    return Path(np.array(points))


@dataclass(frozen=True)
class PhysicsSplit:
    """One split of the physics benchmark: the catalogue vehicles its cars are drawn around (in turn), its tire models
    (drawn), its fixed seed, its number of runs and the range its tires' stiffness scale is drawn from (uniform)."""

    vehicles: tuple[VehicleParams, ...]
    tires: tuple[TireModel, ...]
    seed: int
    runs: int
    stiffness: tuple[float, float]


# pmf's constants were chosen on the paper preset (paper SUV, Dugoff) and on the generalization test runs (compact
# hatchback, all three tires): those vehicles and Dugoff / Magic Formula are the validation split. The midsize sedan with
# Burckhardt's tire is the test split: no constant was chosen on a pmf run of that vehicle with that tire.
# The stiffness: a road's slip curve is the tire's and the surface's. Burckhardt's tabulated surfaces carry their own
# slopes (dry cobblestone's, per unit of peak, is 0.34 of dry asphalt's), so the test split draws the production
# spread around them (+-30 %); Dugoff's and the Magic Formula's slope is the tire's alone, so the validation split draws
# down to cobblestone's (0.3) as well: a slip curve that soft reaches a traction controller's or ABS's slip threshold
# at a fraction of the road's mu.
PHYSICS_SPLITS = {
    "validation": PhysicsSplit(
        (PAPER_SUV, COMPACT_HATCHBACK), (DugoffTire(), MagicFormulaTire()), 2311, 240, (0.3, 1.3)
    ),
    "test": PhysicsSplit((MIDSIZE_SEDAN,), (BurckhardtTire(),), 2399, 240, (0.7, 1.3)),
}


def physics_manoeuvre(rng: np.random.Generator, manoeuvre: str, duration_s: float, mu: float, wheelbase_m: float):
    """(speed profile, path builder, steer input) of one physics-benchmark manoeuvre on a road of friction mu.

    Every manoeuvre is sized by the road's mu (a driver who knows the road): braking and accelerating ask 0.7-1.4 mu g
    (ABS on most stops, traction control on most starts), steering 0.5-0.9 mu g (steering: the neutral-steer angle L a_y / v^2 for it; a ramp steer
    is the first half of a slow sine, up and back down over the run), low-speed tight turns (radius 10-25 m, half of
    them on a circle, half through roundabouts) reach 0.5-0.9 mu g at their end speed."""
    u = rng.uniform(*PHYSICS_UTILIZATION)
    if manoeuvre == "braking_abs":
        v = rng.uniform(15.0, 30.0)
        decel = rng.uniform(*PHYSICS_LIMIT_UTILIZATION) * mu * G_MPS2
        times, speeds, t = [0.0], [v], 0.0
        while t < duration_s:
            for dt, target in ((rng.uniform(2.0, 5.0), v), (v / decel, 0.0), (1.5, 0.0), (v / (u * mu * G_MPS2), v)):
                t += dt
                times.append(t)
                speeds.append(target)
        return SpeedProfile(times, speeds), Path.straight, None
    if manoeuvre == "acceleration":
        v0, v1 = rng.uniform(0.0, 5.0), rng.uniform(20.0, 35.0)
        accel = rng.uniform(*PHYSICS_LIMIT_UTILIZATION) * mu * G_MPS2
        return SpeedProfile([0.0, 2.0, 2.0 + (v1 - v0) / accel], [v0, v0, v1]), Path.straight, None
    if manoeuvre in ("ramp_steer", "sine_steer"):
        v = rng.uniform(10.0, 25.0)
        amplitude = min(wheelbase_m * u * mu * G_MPS2 / v**2, 0.1)
        start_s = 3.0
        frequency = 0.5 / (duration_s - start_s) if manoeuvre == "ramp_steer" else rng.uniform(0.2, 0.6)
        return (
            SpeedProfile([0.0, duration_s], [v, v]),
            Path.straight,
            SteerInput(start_s, duration_s, amplitude, frequency),
        )
    if manoeuvre == "cruise":
        speed, build_path, _, _ = random_manoeuvre(rng, "cruise", duration_s, mu)
        return speed, build_path, None
    if manoeuvre == "tight_turn":
        radius = rng.uniform(*PHYSICS_TIGHT_RADIUS_M)
        v_end = min(math.sqrt(u * mu * G_MPS2 * radius), 15.0)
        speed = SpeedProfile([0.0, 0.6 * duration_s, duration_s], [min(2.0, v_end), v_end, v_end])
        if rng.random() < 0.5:
            return speed, (lambda length: roundabouts(radius, length)), None
        return speed, (lambda length: Path.circle(radius, length)), None
    raise ValueError(f"physics_manoeuvre: manoeuvre must be one of {PHYSICS_MANOEUVRES}, got {manoeuvre!r}")


# A physics run's calm lead-in (physics_lead_in): the driving a fleet car has done before it meets the run's road
# the roads it comes from, drawn apart from the run's: wet or dry asphalt of 0.6 or more, where its calm driving
# (below) stays under half the road's limit
PHYSICS_LEAD_IN_SURFACES = {"wet": (0.6, 0.8), "dry": (0.8, 1.2)}
PHYSICS_LEAD_IN_SPEED_MPS = (8.0, 25.0)
PHYSICS_LEAD_IN_ACCEL_MPS2 = (0.3, 1.5)  # speed changes, stops and starts: under 0.15 g
PHYSICS_LEAD_IN_LATERAL_MPS2 = (0.5, 2.0)  # the curves' lateral acceleration at the top speed
LEAD_IN_SUFFIX = "-lead-in"  # a lead-in's run id: its run's and this
# The run's surface's slope at zero slip against the lead-in's wet or dry asphalt, from Burckhardt's table (Kiencke and
# Nielsen, Automotive Control Systems): asphalt and concrete, dry or wet, 28.6-30.2 per unit slip; wet cobblestone 13.4,
# dry cobblestone 8.2, snow 18.3, ice 15.3. A tire model whose slope is the same on every surface (Dugoff, the Magic
# Formula) has it put in its stiffness scale on the lead-in: the run's divided by this
PHYSICS_SURFACE_SLOPE = {"ice": (0.45, 0.6), "snow": (0.55, 0.7), "wet": (0.45, 1.0), "dry": (0.28, 1.0)}


def physics_lead_in(scenario: Scenario, seconds: float) -> Scenario:
    """The calm drive the same car made before a physics-benchmark run: `seconds` on a winding road (curvature a sine
    along it, PHYSICS_LEAD_IN_LATERAL_MPS2 at the top speed) of wet or dry asphalt drawn apart from the run's, with
    gentle speed changes and a stop now and then (PHYSICS_LEAD_IN_ACCEL_MPS2). The run's vehicle, tire and effects, and
    its seed, so that the per-car draws of its production effects (radii, mounting, biases) are the run's; its own
    draws come from a generator of (the run's seed, 1), so the run is unchanged. The tire's slope on the lead-in's
    asphalt is the run's over PHYSICS_SURFACE_SLOPE of the run's surface (`scenario.condition`), drawn, where the tire
    model's slope is the same on every surface; Burckhardt's carries its own."""
    if not seconds > 0:
        raise ValueError(f"a lead-in lasts more than 0 s, got {seconds!r}")
    rng = np.random.default_rng([scenario.seed, 1])
    low, high = PHYSICS_LEAD_IN_SPEED_MPS
    times, speeds = [0.0], [float(rng.uniform(low, high))]

    def go(dt, v):
        times.append(times[-1] + dt)
        speeds.append(v)

    while times[-1] < seconds:
        if rng.random() < 0.25:  # a stop and a start
            go(speeds[-1] / rng.uniform(*PHYSICS_LEAD_IN_ACCEL_MPS2), 0.0)
            go(rng.uniform(2.0, 6.0), 0.0)
        target = float(rng.uniform(low, high))
        go(abs(target - speeds[-1]) / rng.uniform(*PHYSICS_LEAD_IN_ACCEL_MPS2) + 0.1, target)
        go(rng.uniform(3.0, 10.0), target)
    speed = SpeedProfile(times, speeds)
    distance_m = speed.distance_m(seconds)
    step_m, wavelength_m = 2.0, rng.uniform(300.0, 600.0)
    curvature = rng.uniform(*PHYSICS_LEAD_IN_LATERAL_MPS2) / high**2
    s = np.arange(0.0, 1.2 * distance_m + 300.0, step_m)
    heading = np.cumsum(curvature * np.sin(2.0 * math.pi * s / wavelength_m + rng.uniform(0.0, 2.0 * math.pi))) * step_m
    points = np.column_stack([np.cumsum(np.cos(heading)), np.cumsum(np.sin(heading))]) * step_m
    surface = tuple(PHYSICS_LEAD_IN_SURFACES)[int(rng.integers(len(PHYSICS_LEAD_IN_SURFACES)))]
    tire = scenario.tire
    if not tire.slope_by_surface:
        slope = float(rng.uniform(*PHYSICS_SURFACE_SLOPE[scenario.condition]))
        tire = dataclasses.replace(tire, stiffness_scale=min(tire.stiffness_scale / slope, STIFFNESS_SCALE_BOUNDS[1]))
    return scenario.replace(
        run_id=f"{scenario.run_id}{LEAD_IN_SUFFIX}",
        path=Path(np.vstack([[0.0, 0.0], points])),
        mu=MuProfile.uniform(float(rng.uniform(*PHYSICS_LEAD_IN_SURFACES[surface]))),
        tire=tire,
        speed=speed,
        condition=surface,
        road="curve",
        steer=None,
        duration_s=seconds,
        manoeuvre="lead_in",
        grade=random_grade(rng, scenario.effects.grade_max_rad, distance_m),
    )


def physics_benchmark_runs(split: str, runs: int | None = None) -> list[tuple[Scenario, VehicleParams]]:
    """(scenario, catalogue entry its vehicle was drawn around) of every run of a physics-benchmark split.

    Run k: manoeuvre k mod 6, surface (ice, snow, wet, dry: PHYSICS_SURFACES) k div 6 mod 4, so that 24 runs hold every
    pair once, and catalogue entry k div 24 (round robin over the split's); mu constant over the run, uniform in the
    surface's range; the vehicle drawn around the entry (docs/VEHICLES.md ranges) with the entry's drive layout (the
    variant a fleet registers); the split's tire model and its stiffness factor (in the split's range) drawn; a graded
    road and every production-terminal effect on."""
    check_choice("physics benchmark", "split", split, set(PHYSICS_SPLITS))
    spec = PHYSICS_SPLITS[split]
    n = spec.runs if runs is None else runs
    if n < 1:
        raise ValueError(f"physics benchmark runs must be >= 1, got {n!r}")
    surfaces = tuple(PHYSICS_SURFACES)
    pairs = len(PHYSICS_MANOEUVRES) * len(surfaces)
    out = []
    for k, run_seed in enumerate(_run_seeds(spec.seed, n)):
        rng = np.random.default_rng(run_seed)
        manoeuvre = PHYSICS_MANOEUVRES[k % len(PHYSICS_MANOEUVRES)]
        surface = surfaces[(k // len(PHYSICS_MANOEUVRES)) % len(surfaces)]
        mu = float(rng.uniform(*PHYSICS_SURFACES[surface]))
        base = spec.vehicles[(k // pairs) % len(spec.vehicles)]
        run_id = f"physics-{split}-{k:04d}"
        vehicle = random_vehicle(rng, run_id, (base,)).replace(
            drive=base.drive, front_drive_share=base.front_drive_share
        )
        speed, build_path, steer = physics_manoeuvre(rng, manoeuvre, PHYSICS_DURATION_S, mu, vehicle.wheelbase_m)
        distance_m = speed.distance_m(PHYSICS_DURATION_S)
        tire = spec.tires[int(rng.integers(len(spec.tires)))]
        tire = dataclasses.replace(tire, stiffness_scale=float(rng.uniform(*spec.stiffness)))
        scenario = Scenario(
            run_id=run_id,
            path=build_path(1.3 * distance_m + 300.0),
            mu=MuProfile(np.array([0.0]), np.array([mu]), np.array([mu]), "step"),
            speed=speed,
            condition=surface,
            road="curve" if manoeuvre == "tight_turn" else "straight",
            vehicle=vehicle,
            tire=tire,
            steer=steer,
            duration_s=PHYSICS_DURATION_S,
            seed=run_seed,
            manoeuvre=manoeuvre,
            grade=random_grade(rng, RANDOM_EFFECTS.grade_max_rad, distance_m),
            effects=RANDOM_EFFECTS,
        )
        out.append((scenario, base))
    return out
