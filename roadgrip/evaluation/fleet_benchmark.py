"""The fleet benchmark (issue 16, items 1-2): a simulated fleet drives a road network for an hour while patches of ice,
snow, slush and wet road come and go; its telemetry goes through the cloud service's own ingest path (the same code as
`roadgrip serve`: per-vehicle estimators, storage, map, warning engine), in this process and far faster than real time;
then the warnings and the map are scored against the truth.

Scenario (one per seed, `make_scenario`):
- the generated network (roadgrip.fleet.network.generated_network) without its fixed patches; `patches_per_band`
  patches in each band of BANDS (mu drawn uniformly in the band) and `control_patches` wet ones (mu 0.80, the
  Burckhardt wet asphalt: not slippery), discs of 40-70 m radius on one road each, away from the other roads and from
  each other; each appears at a time uniform in [0, appear_max_s] and dries up `life_s` later (uniform range), inside
  the run;
- `vehicles` vehicles (kinds cycling over the shipped ones, production-terminal effects on: ProductionEffects.production,
  a tire stiffness factor drawn per vehicle, a grade per road; a `channel_share` of them, spread evenly, also sending
  every optional channel: GNSS speed, drive and brake force, steering torques, with roadgrip/sim/channels.py's error
  models), each with a driver style drawn from STYLES (most gentle,
  some firm, a few braking hard); each drives trips one after the other for the whole run: a road of the network
  (either direction, uniform) end to end at its cruising speed (x U(0.9, 1.05)), braking now and then at random
  stations (BRAKINGS_PER_KM by road kind: junctions in town, merges, traffic) at its style's deceleration to 40 % of the
  cruise, then back up; a pause of TRIP_GAP_S between trips. A trip's patches are those there when it reaches them
  (Network.mu_profile with the planned arrival clock).

Roadside stations (issue 16, item 4; issue 23; `simulate_station_reports`): `stations` road weather stations where a
road operator would put them, chosen from the network alone, never from the patches (`place_stations`): evenly along
the network's roads laid end to end, one every (total length / stations) metres from a seeded random offset. Where a
station happens to stand on a patch is the truth's business (SimStation.patch, for the report only). Each reports
every STATION_REPORT_S (60 s, from a random phase) what its sensors read at its spot, in report format v1
(roadgrip/cloud/domain/stations.py):
- surface state from the true mu there (`state_of`: <= 0.2 ice, <= 0.4 snow, < 0.65 wet with a 1-3 mm film, < 0.95
  wet with a 0.05-0.2 mm film, else dry), moved one class along ice-snow-wet-moist-dry with probability
  STATION_CONFUSION (0.1) per report: the misclassifications of optical sensors (an assumption of about one report in
  ten, not a measured rate: the classes border each other, moist against wet, snow against ice); a surface
  temperature that goes with it (ice and snow -8..-1 C, else 1..8 C);
- every other station (the odd ones) also has a friction sensor: the true mu capped at 1, plus the sensor's own bias
  (drawn once per station, uniform in +-STATION_FRICTION_BIAS, 0.1) and N(0, STATION_FRICTION_NOISE, 0.05) per
  reading, clipped to [0, 1], with its class's +-0.1 uncertainty. The bias: optical sensors infer friction from the
  layer they see, not from a tire, and are calibrated per site; a bias of up to the +-0.1 class width that
  stations.py already gives a reading (FRICTION_UNCERTAINTY) is the assumption, not a datasheet figure;
- failures: each report is lost with probability STATION_LOSS (0.05); with probability 0.3 a station is out for one
  spell of 10-30 min (no reports); with probability 0.2 it sticks for 10-20 min from a random instant, repeating the
  reading it had then with new timestamps (a frozen sensor).
Stations change no vehicle's estimate: the warnings without them are the service's warning engine's own input
replayed without the station rounds (EngineRecorder, roadgrip/evaluation/fleet_sweep.py).

Service: a CloudService (SQLite in a temporary folder, MQTT off, map_clock "data", no per-vehicle rate limit: the fleet
is sent faster than real time) with the product's defaults otherwise (estimator pmf, warning and map settings). Every
vehicle's samples go in timestamp order, one second (10 samples) a message, through `parse_payload` and
`service.ingest.submit`: what the HTTP route does after authentication. The map is read at `snapshot_every_s`. In
edge mode (`run_service(mode="edge")`) each vehicle estimates on board instead and its friction observations reach
the service (roadgrip/evaluation/fleet_edge.py).

Definitions (docs/RESULTS.md, "The fleet benchmark"):
- pass: a vehicle's consecutive samples on a patch (inside its disc) while the patch is there (the simulator's true mu
  under the vehicle is the patch's); its time is when it entered;
- patch cells: the H3 cells (the service's resolution) of the road points inside the patch;
- a warning is on a patch when its cell is a patch cell and it was raised while the patch was there; it is beside a
  patch when its cell neighbours a patch cell (k = 1) or it was raised within the warning validity after the patch
  dried; otherwise it is false. Warnings on control (wet, mu 0.80) patches are false;
- detected: a warning on the patch; time to first warning: its detection time less the patch's appearance;
  passes to first warning: the passes that entered the patch up to the detection time;
- linger: how long after the last ice the fleet drove on the last of the patch's warnings ended (cancelled or expired;
  a warning still active at the end counts to the end and is flagged censored); the last ice is the patch's drying
  time, or later when a trip that planned to reach it before then drove it after (fleet_metrics.patch_outcome);
- dry road: road whose true mu under the vehicle is at least 0.6 (fleet_metrics.DRY_MU: dry asphalt, or a wet control
  patch); false warnings per 100 km of dry road = false warnings / (km driven on dry road / 100);
- map error at an instant: for each cell with recent excited evidence (status measured), the distance from the map's mu
  to the range of the true mu over the road points of the cell at that instant (a cell may hold patch and dry road);
  covered when the map's 90 % interval meets that range; its band is that of the lowest true mu in it;
- evidence share: of the cells driven in the last EVIDENCE_WINDOW_S before an instant, the share with recent excited
  evidence on the map.

Size: over 500 lines because one experiment: the fleet's hour through the service and its scoring against the truth,
which share the run's timeline.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import h3
import numpy as np
import orjson
import pyarrow as pa
import pymap3d

from roadgrip.cloud.domain.stations import parse_reports
from roadgrip.cloud.ingest.wire import parse_payload
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.evaluation.bins import true_utilization
from roadgrip.evaluation.fleet_edge import EdgeFleet
from roadgrip.fleet.fleet import _speed_profile, planned_arrival
from roadgrip.fleet.network import SURFACE_MU, Network, Patch, Road, generated_network, points_at
from roadgrip.sim.presets import random_grade
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import GradeProfile
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import VEHICLES
from roadgrip.vehicle.tires import DugoffTire

log = logging.getLogger(__name__)

BANDS = (("mu<=0.2", 0.05, 0.2), ("0.2-0.4", 0.2, 0.4), ("0.4-0.6", 0.4, 0.6))  # name, low, high (mu)
CONTROL_MU = SURFACE_MU["wet"]  # 0.80: wet asphalt, not slippery
# driver styles: (share of drivers, braking deceleration, re-acceleration), m/s^2
STYLES = {
    "gentle": (0.70, 0.15 * G_MPS2, 0.10 * G_MPS2),
    "firm": (0.25, 0.30 * G_MPS2, 0.15 * G_MPS2),
    "hard": (0.05, 0.60 * G_MPS2, 0.20 * G_MPS2),
}
BRAKINGS_PER_KM = {"urban": 2.0, "ramp": 1.0, "expressway": 0.4}  # junctions and traffic in town, a merge, traffic
TRIP_GAP_S = (5.0, 60.0)  # pause between two trips of one vehicle (parking, a road not in the network)
PATCH_RADIUS_M = (40.0, 70.0)
PATCH_CLEARANCE_M = 150.0  # between patch edges, and from a patch to any other road
EVIDENCE_WINDOW_S = 600.0
WAIT_STEP_S = 0.01
STATION_REPORT_S = 60.0
STATION_CONFUSION = 0.1  # a report's state one class off
STATION_LOSS = 0.05  # a report lost
STATION_FRICTION_NOISE = 0.05  # standard deviation of a friction sensor's reading
STATION_FRICTION_BIAS = 0.1  # a friction sensor's own bias: uniform in +- this, drawn once per station
STATE_ORDER = ("ice", "snow", "wet", "moist", "dry")  # a misread moves one step along
EXCITED_UTILIZATION = 0.5  # CONTRACTS 4: an excited sample
OBSERVABLE_SAMPLES = 3  # excited samples that make a pass observable (the warning engine's min_excited_per_pass)


@dataclass(frozen=True)
class FleetConfig:
    vehicles: int = 32
    duration_s: float = 3600.0
    patches_per_band: int = 3
    control_patches: int = 2
    appear_max_s: float = 1200.0  # patches appear in [0, appear_max_s] ...
    life_s: tuple[float, float] = (900.0, 1800.0)  # ... and dry up this long after
    snapshot_every_s: float = 300.0
    stations: int = 6  # roadside stations, evenly along the network (place_stations)
    channel_share: float = 0.0  # share of the vehicles that send every optional channel (CONTRACTS 3.1; issue 26)

    def __post_init__(self):
        if self.vehicles < 1:
            raise ValueError(f"vehicles must be >= 1, got {self.vehicles!r}")
        if not 60.0 <= self.duration_s <= 3 * 3600.0:
            raise ValueError(f"duration_s must lie in [60, 10800], got {self.duration_s!r}")
        if self.stations < 0:
            raise ValueError(f"stations must be >= 0, got {self.stations!r}")
        if not 0.0 <= self.channel_share <= 1.0:
            raise ValueError(f"channel_share must lie in [0, 1], got {self.channel_share!r}")
        if not 0 < self.life_s[0] <= self.life_s[1]:
            raise ValueError(f"life_s must be (low, high) with 0 < low <= high, got {self.life_s!r}")


@dataclass(frozen=True)
class Trip:
    vehicle_id: str
    style: str
    depart_s: float
    scenario: Scenario


@dataclass(frozen=True)
class FleetScenario:
    seed: int
    config: FleetConfig
    network: Network
    trips: tuple[Trip, ...]
    styles: dict = field(default_factory=dict)  # vehicle_id -> style
    kinds: dict = field(default_factory=dict)  # vehicle_id -> VehicleParams
    with_channels: frozenset = frozenset()  # the vehicles that send the optional channels (FleetConfig.channel_share)


# --------------------------------------------------------------------------------------------------- scenario
def _place_patches(rng: np.random.Generator, roads: tuple[Road, ...], config: FleetConfig) -> tuple[Patch, ...]:
    wanted = [
        (name, surface, float(rng.uniform(low, high)))
        for (name, low, high), surface in zip(BANDS, ("ice", "snow", "wet"))
        for _ in range(config.patches_per_band)
    ]
    wanted += [("control", "wet", None)] * config.control_patches
    lengths = np.array([r.path.length_m for r in roads])
    placed: list[Patch] = []
    for k, (band, surface, mu) in enumerate(wanted):
        for _ in range(500):
            i = int(rng.choice(len(roads), p=lengths / lengths.sum()))
            road, radius = roads[i], float(rng.uniform(*PATCH_RADIUS_M))
            east, north = points_at(road.path, np.array([rng.uniform(0.15, 0.85) * road.path.length_m]))[0]
            clear = all(
                math.hypot(east - p.east_m, north - p.north_m) > radius + p.radius_m + PATCH_CLEARANCE_M for p in placed
            )
            clear = clear and all(
                np.hypot(*(other.points_m - [east, north]).T).min() > radius + PATCH_CLEARANCE_M
                for j, other in enumerate(roads)
                if j != i
            )
            if clear:
                break
        else:
            raise ValueError(f"no room for patch {k} on the network: fewer patches or a larger network")
        appear = float(rng.uniform(0.0, config.appear_max_s))
        dry = min(appear + float(rng.uniform(*config.life_s)), config.duration_s)
        placed.append(Patch(f"{band}-{k:02d}", surface, float(east), float(north), radius, mu, appear, dry))
    return tuple(placed)


def _reversed_grade(grade: GradeProfile, length_m: float) -> GradeProfile:
    """The grade of the road driven the other way: stations mirrored, uphill becomes downhill."""
    stations = np.concatenate([[0.0], length_m - grade.stations_m[::-1]])
    values = np.concatenate([[-grade.grade_rad[-1]], -grade.grade_rad[::-1]])
    keep = np.concatenate([[True], np.diff(stations) > 1e-6])
    return GradeProfile(stations[keep], values[keep])


def make_scenario(seed: int, config: FleetConfig = FleetConfig()) -> FleetScenario:
    """The network with this seed's patches, and every vehicle's trips over the run (see the module docstring)."""
    rng = np.random.default_rng(seed)
    base = generated_network()
    network = Network(base.roads, _place_patches(rng, base.roads, config), base.origin)
    effects = ProductionEffects.production()
    routes = []  # (road, its grade)
    for road in network.roads:
        grade = random_grade(rng, effects.grade_max_rad, road.path.length_m)
        routes += [(road, grade), (road.reversed(), _reversed_grade(grade, road.path.length_m))]
    names = list(STYLES)
    shares = np.array([STYLES[n][0] for n in names])
    kinds = list(VEHICLES.values())
    trips, styles, vehicle_kinds, with_channels = [], {}, {}, set()
    for v in range(config.vehicles):
        vehicle_id = f"bench-{v:03d}"
        # spread evenly over the fleet (and so over the kinds, which cycle); no draw, so the rest of the scenario is
        # the same whatever the share
        sends_channels = math.floor((v + 1) * config.channel_share) > math.floor(v * config.channel_share)
        if sends_channels:
            with_channels.add(vehicle_id)
        style = names[int(rng.choice(len(names), p=shares / shares.sum()))]
        _, brake, accel = STYLES[style]
        vehicle = kinds[v % len(kinds)]
        tire = dataclasses.replace(
            DugoffTire(),
            stiffness_scale=float(rng.uniform(1 - effects.tire_stiffness_spread, 1 + effects.tire_stiffness_spread)),
        )
        # one terminal's seed: its speed scale and production effects (mounting, radii) stay with the vehicle; the IMU,
        # gyro and steering biases come out different each trip (drawn after noise as long as the trip), as a MEMS
        # gyro's do at each power-on (docs/RESULTS.md, "A new trip's gyro bias")
        sensor_seed = int(rng.integers(2**31))
        styles[vehicle_id], vehicle_kinds[vehicle_id] = style, vehicle
        t = float(rng.uniform(0.0, 60.0))
        k = 0
        while t < config.duration_s - 30.0:
            road, grade = routes[int(rng.integers(len(routes)))]
            length = road.path.length_m
            cruise = road.cruise_mps * float(rng.uniform(0.9, 1.05))
            n_brakes = int(rng.poisson(BRAKINGS_PER_KM[road.kind] * length / 1000.0))
            brakes = sorted(rng.uniform(0.05 * length, 0.85 * length, size=n_brakes).tolist())
            speed, duration = _speed_profile(
                cruise, brakes, length, config.duration_s - t, brake_mps2=brake, reaccelerate_mps2=accel
            )
            duration = math.floor(duration * 10) / 10
            if duration < 10.0:
                break
            mu = network.mu_profile(road, planned_arrival(speed, t))
            trips.append(
                Trip(
                    vehicle_id,
                    style,
                    round(t, 1),
                    Scenario(
                        run_id=f"{vehicle_id}-{k:03d}",
                        path=road.path,
                        mu=mu,
                        speed=speed,
                        vehicle=vehicle,
                        tire=tire,
                        duration_s=duration,
                        seed=sensor_seed,
                        condition="fleet",
                        road=road.name,
                        manoeuvre=style,
                        grade=grade,
                        effects=effects.with_channels() if sends_channels else effects,
                    ),
                )
            )
            t = round(t + duration + float(rng.uniform(*TRIP_GAP_S)), 1)
            k += 1
    return FleetScenario(seed, config, network, tuple(trips), styles, vehicle_kinds, frozenset(with_channels))


# --------------------------------------------------------------------------------------------------- stations
@dataclass(frozen=True)
class SimStation:
    station_id: str
    east_m: float
    north_m: float
    patch: str | None  # the patch whose disc holds its spot (truth, for the report; not used to place it), or None
    friction_sensor: bool
    friction_bias: float = 0.0  # its friction sensor's bias (STATION_FRICTION_BIAS)


def state_of(mu: float, rng: np.random.Generator) -> tuple[str, float | None]:
    """The surface state a station reads for a true mu, and its water film (mm)."""
    if mu <= 0.2:
        return "ice", 0.0
    if mu <= 0.4:
        return "snow", 0.0
    if mu < 0.65:
        return "wet", float(rng.uniform(1.0, 3.0))
    if mu < 0.95:
        return "wet", float(rng.uniform(0.05, 0.2))
    return "dry", 0.0


def place_stations(scenario: FleetScenario, rng: np.random.Generator) -> list[SimStation]:
    """`stations` sites evenly along the network's roads laid end to end (one every total / stations metres, from an
    offset uniform in the first interval), chosen from the network alone; the odd ones with a friction sensor and its
    bias. Which patch, if any, holds a site is looked up afterwards, for the report."""
    config, network = scenario.config, scenario.network
    lengths = np.array([road.path.length_m for road in network.roads])
    ends = np.cumsum(lengths)
    spacing = float(ends[-1]) / max(1, config.stations)
    offset = float(rng.uniform(0.0, spacing))
    stations = []
    for k in range(config.stations):
        along = offset + k * spacing
        i = min(int(np.searchsorted(ends, along, side="right")), len(lengths) - 1)
        road = network.roads[i]
        east, north = points_at(road.path, np.array([along - (ends[i] - lengths[i])]))[0]
        holder = next((p.name for p in network.patches if p.contains(east, north)), None)
        bias = float(rng.uniform(-STATION_FRICTION_BIAS, STATION_FRICTION_BIAS)) if k % 2 == 1 else 0.0
        stations.append(SimStation(f"rws-{k:02d}", float(east), float(north), holder, k % 2 == 1, bias))
    return stations


def simulate_station_reports(scenario: FleetScenario, start_ms: int) -> tuple[list[SimStation], list[tuple]]:
    """The stations (`place_stations`) and every report they send over the run, (t_s, report dict) in time order, with
    their sensors' misreadings and failures (module docstring)."""
    rng = np.random.default_rng([scenario.seed, 16])  # a stream of its own: the scenario's draws stay as they were
    network, duration_s = scenario.network, scenario.config.duration_s
    stations = place_stations(scenario, rng)
    origin = network.origin
    out = []
    for station in stations:
        lat, lon, _ = pymap3d.enu2geodetic(station.east_m, station.north_m, 0.0, *origin, 0.0)
        outage = (-1.0, -1.0)
        if rng.random() < 0.3:
            begin = float(rng.uniform(0.0, duration_s))
            outage = (begin, begin + float(rng.uniform(600.0, 1800.0)))
        stuck = (-1.0, -1.0)
        if rng.random() < 0.2:
            begin = float(rng.uniform(0.0, duration_s))
            stuck = (begin, begin + float(rng.uniform(600.0, 1200.0)))
        frozen = None
        for t in np.arange(float(rng.uniform(0.0, STATION_REPORT_S)), duration_s, STATION_REPORT_S).tolist():
            mu = network.dry_mu
            for patch in network.patches:
                if patch.active(t) and patch.contains(station.east_m, station.north_m):
                    mu = min(mu, patch.mu)
            state, film = state_of(mu, rng)
            if rng.random() < STATION_CONFUSION:
                k = STATE_ORDER.index(state) + (1 if rng.random() < 0.5 else -1)
                state = STATE_ORDER[min(len(STATE_ORDER) - 1, max(0, k))]
            reading = {
                "surface_state": state,
                "water_film_thickness_mm": film,
                "surface_temperature_c": round(
                    float(rng.uniform(-8.0, -1.0) if state in ("ice", "snow") else rng.uniform(1.0, 8.0)), 1
                ),
            }
            if station.friction_sensor:
                friction = min(1.0, mu) + station.friction_bias + float(rng.normal(0.0, STATION_FRICTION_NOISE))
                reading.update(friction=round(min(1.0, max(0.0, friction)), 3), friction_uncertainty=0.1)
            if stuck[0] <= t < stuck[1]:
                frozen = frozen or reading
                reading = frozen
            lost = outage[0] <= t < outage[1] or rng.random() < STATION_LOSS
            if not lost:
                out.append(
                    (
                        round(t, 1),
                        {
                            "station_id": station.station_id,
                            "timestamp_ms": start_ms + round(t * 1000),
                            "latitude_deg": float(lat),
                            "longitude_deg": float(lon),
                            **reading,
                        },
                    )
                )
    out.sort(key=lambda item: (item[0], item[1]["station_id"]))
    return stations, out


# --------------------------------------------------------------------------------------------------- drives
@dataclass
class Drives:
    """Every sample of the run in timestamp order: `table` holds the wire-format telemetry (what the terminals send)
    with timestamps on the data clock; the rest the truth beside it."""

    table: pa.Table
    t_s: np.ndarray  # seconds from the run's start
    vehicle: np.ndarray  # vehicle_id per sample (object array)
    east_m: np.ndarray
    north_m: np.ndarray
    mu: np.ndarray  # true mu under the vehicle
    distance_m: np.ndarray  # driven in the 100 ms before the sample
    cell: np.ndarray  # H3 cell of the reported position (object array)
    start_ms: int
    excited: np.ndarray  # CONTRACTS 4: friction utilization >= 0.5 (bins.true_utilization) or ABS active


def _sensors(network: Network) -> SensorModel:
    """The fleet's sensor model: positions about the network's origin."""
    return SensorModel(origin_lat_deg=network.origin[0], origin_lon_deg=network.origin[1])


def _fleet_clock(table: pa.Table, depart: dict[str, float]) -> tuple[np.ndarray, np.ndarray]:
    """The simulated rows in time order on the fleet's clock (each trip's t_s after its departure, `depart` by run id):
    the order (stable) and the ordered times (s)."""
    t_s = np.array([depart[r] for r in table["run_id"].to_pylist()]) + table["t_s"].to_numpy()
    order = np.argsort(t_s, kind="stable")
    return order, t_s[order]


def vehicle_drive(scenario: FleetScenario, vehicle_id: str, until_s: float = math.inf) -> tuple[pa.Table, np.ndarray]:
    """One vehicle's trips that depart before `until_s`, simulated and put in time order on simulate_drives' clock
    (start 0), with a segment id per trip (an estimator restarts between trips, as the service's does after a gap):
    the car replayed offline through an estimator."""
    trips = [t for t in scenario.trips if t.vehicle_id == vehicle_id and t.depart_s < until_s]
    table = simulate([t.scenario for t in trips], sensors=_sensors(scenario.network), start_epoch_ms=0)
    order, t_s = _fleet_clock(table, {t.scenario.run_id: t.depart_s for t in trips})
    table = table.take(pa.array(order))
    k = table.column_names.index("timestamp_ms")
    table = table.set_column(k, table.schema.field(k), pa.array(np.round(t_s * 1000.0).astype(np.int64)))
    trip_of = {t.scenario.run_id: n for n, t in enumerate(trips)}
    return table, np.array([trip_of[r] for r in table["run_id"].to_pylist()], dtype=np.int64)


def simulate_drives(scenario: FleetScenario, start_ms: int, resolution: int = 10) -> Drives:
    """Simulate every trip; the samples of all vehicles on one clock starting at `start_ms`."""
    table = simulate([trip.scenario for trip in scenario.trips], sensors=_sensors(scenario.network), start_epoch_ms=0)
    runs = {trip.scenario.run_id: trip for trip in scenario.trips}
    order, t_s = _fleet_clock(table, {r: trip.depart_s for r, trip in runs.items()})
    vehicle = np.array([runs[r].vehicle_id for r in table["run_id"].to_pylist()], dtype=object)[order]
    t_s = np.round(t_s, 1)
    wire = [
        c
        for c in TELEMETRY_COLUMNS
        if c in table.column_names and c not in ("vehicle_id", "timestamp_ms", "lateral_speed_mps")
    ]
    telemetry = table.select(wire).take(pa.array(order))  # a production terminal has no lateral speed
    timestamps = start_ms + np.round(t_s * 1000.0).astype(np.int64)
    telemetry = telemetry.append_column("vehicle_id", pa.array(vehicle.tolist(), pa.string()))
    telemetry = telemetry.append_column("timestamp_ms", pa.array(timestamps, pa.int64()))
    speed = table["speed_mps"].to_numpy()[order]
    lat = telemetry["latitude_deg"].to_numpy()
    lon = telemetry["longitude_deg"].to_numpy()
    cells = np.array([h3.latlng_to_cell(a, b, resolution) for a, b in zip(lat.tolist(), lon.tolist())], dtype=object)
    mu = table["mu"].to_numpy()[order]
    utilization = true_utilization(table["ax_true_mps2"].to_numpy()[order], table["ay_true_mps2"].to_numpy()[order], mu)
    excited = (utilization >= EXCITED_UTILIZATION) | telemetry["abs_active"].to_numpy(zero_copy_only=False)
    return Drives(
        telemetry,
        t_s,
        vehicle,
        table["x_m"].to_numpy()[order],
        table["y_m"].to_numpy()[order],
        mu,
        np.abs(speed) * 0.1,
        cells,
        start_ms,
        excited,
    )


# --------------------------------------------------------------------------------------------------- service
@dataclass
class ServiceRun:
    warnings: list[dict]  # storage rows: the latest event of every warning raised
    snapshots: dict[float, list]  # t_s -> the map's CellSummary list at that instant
    samples_sent: int
    rejected: int
    stats: dict
    wall_s: float
    estimates: pa.Table | None = None  # every estimate row the warning engine took, in order (EngineRecorder)
    stations: pa.Table | None = None  # every station evidence row it took (EngineRecorder.station_table)
    station_reports: int = 0  # reports the stations sent
    station_sites: tuple = ()  # the SimStations


REPLAY_FIELDS = (
    "vehicle_id",
    "timestamp_ms",
    "latitude_deg",
    "longitude_deg",
    "mu_lower",
    "mu_upper",
    "excited",
    "mu_proven",
)
STATION_SCHEMA = pa.schema(
    [
        ("round", pa.int64()),
        ("now_ms", pa.int64()),
        ("station_id", pa.string()),
        ("cell", pa.string()),
        ("timestamp_ms", pa.int64()),
        ("mu", pa.float64()),
        ("mu_lower", pa.float64()),
        ("mu_upper", pa.float64()),
    ]
)
REPLAY_SCHEMA = pa.schema(
    [
        ("round", pa.int64()),
        ("now_ms", pa.int64()),
        ("vehicle_id", pa.string()),
        ("timestamp_ms", pa.int64()),
        ("latitude_deg", pa.float64()),
        ("longitude_deg", pa.float64()),
        ("mu_lower", pa.float64()),
        ("mu_upper", pa.float64()),
        ("excited", pa.bool_()),
        ("mu_proven", pa.float64()),
    ]
)


class EngineRecorder:
    """Stands in for the service's WarningEngine and passes every call on to it, keeping what each `update` took:
    the round (one call of Fanout), the service clock `now_ms` it was called with, and the fields of every estimate
    row the engine reads (REPLAY_FIELDS), in the order given. `table()` holds them as REPLAY_SCHEMA; the roadside
    stations' evidence (`station_evidence` calls, rounds counted with the others) `station_table()` as STATION_SCHEMA.
    roadgrip/evaluation/fleet_sweep.py replays them into engines with other settings."""

    def __init__(self, engine):
        self.engine = engine
        self._columns: dict[str, list] = {name: [] for name in REPLAY_SCHEMA.names}
        self._station_columns: dict[str, list] = {name: [] for name in STATION_SCHEMA.names}
        self._rounds = 0

    def __getattr__(self, name):
        return getattr(self.engine, name)

    def update(self, estimates, now_ms: int):
        estimates = list(estimates)
        columns = self._columns
        columns["round"].extend([self._rounds] * len(estimates))
        columns["now_ms"].extend([int(now_ms)] * len(estimates))
        for name in REPLAY_FIELDS:
            columns[name].extend([row[name] for row in estimates])
        self._rounds += 1
        return self.engine.update(estimates, now_ms)

    def station_evidence(self, rows, now_ms: int):
        rows = list(rows)
        columns = self._station_columns
        columns["round"].extend([self._rounds] * len(rows))
        columns["now_ms"].extend([int(now_ms)] * len(rows))
        for name in STATION_SCHEMA.names[2:]:
            columns[name].extend([row[name] for row in rows])
        self._rounds += 1
        return self.engine.station_evidence(rows, now_ms)

    def table(self) -> pa.Table:
        return pa.Table.from_pydict(self._columns, schema=REPLAY_SCHEMA)

    def station_table(self) -> pa.Table:
        return pa.Table.from_pydict(self._station_columns, schema=STATION_SCHEMA)


def _wait_idle(service: CloudService) -> None:
    """Until the pipeline has taken everything submitted and released its reorder windows into the map."""
    while service.ingest.backlog:
        time.sleep(WAIT_STEP_S)
    time.sleep(service.settings.reorder_window_s + 2 * service.settings.flush_interval_s)
    while service.ingest.backlog:
        time.sleep(WAIT_STEP_S)


def run_service(
    scenario: FleetScenario,
    drives: Drives,
    data_dir: Path,
    *,
    max_backlog: int = 20_000,
    progress: Callable[[float], None] | None = None,
    mode: str = "raw",
    **settings,
) -> ServiceRun:
    """Feed the drives to a CloudService through its ingest path (parse_payload, then ingest.submit, as the HTTP
    route does), one second of every vehicle a message, in timestamp order; read the map at each snapshot instant.
    Mode edge: each vehicle's second of samples goes into its own agent instead, and its observations and
    heartbeats to the service (roadgrip/evaluation/fleet_edge.py)."""
    if mode not in ("raw", "edge"):
        raise ValueError(f"mode must be raw or edge, got {mode!r}")
    settings = Settings(
        **{
            "data_dir": data_dir,
            "mqtt": "off",
            "map_clock": "data",
            "rate_limit_samples_per_s": 0,
            "admin_secret": "fleet-benchmark-admin",
            **settings,
        }
    )
    started = time.perf_counter()
    snapshots: dict[float, list] = {}
    rejected = sent = station_sent = 0
    every = scenario.config.snapshot_every_s
    instants = [float(t) for t in np.arange(every, scenario.config.duration_s + 1e-6, every)]
    stations, reports = simulate_station_reports(scenario, drives.start_ms)
    service = CloudService(settings)
    recorder = service.warning_engine = EngineRecorder(service.warning_engine)  # before start: Fanout takes it there
    with service:
        service.register_vehicles(sorted(scenario.kinds.items()))
        edge = EdgeFleet(scenario, data_dir / "edge", service.settings) if mode == "edge" else None
        for station in stations:
            service.register_station(station.station_id)
        s = service.settings
        second = np.floor(drives.t_s).astype(np.int64)
        bounds = np.flatnonzero(np.diff(second)) + 1
        starts = np.concatenate([[0], bounds])
        ends = np.concatenate([bounds, [second.size]])
        futures = []
        chunk_rows, chunk_start = [], 0
        for a, b in zip(starts.tolist(), ends.tolist()):
            if a >= chunk_start + len(chunk_rows):  # rows come 60 s of data at a time (to_pylist is per call)
                chunk_start, stop = a, int(np.searchsorted(second, second[a] + 60))
                chunk_rows = drives.table.slice(a, stop - a).to_pylist()
            by_vehicle: dict[str, list] = {}
            for row in chunk_rows[a - chunk_start : b - chunk_start]:
                by_vehicle.setdefault(row["vehicle_id"], []).append(row)
            now_ms = int(time.time() * 1000)
            t_end = float(second[a] + 1)
            if edge is not None:
                for vehicle_id, rows in by_vehicle.items():
                    edge.feed(vehicle_id, rows)
                    sent += len(rows)
                edge.ignition_off(t_end)
                edge.deliver(service)
                by_vehicle = {}
            for vehicle_id, rows in by_vehicle.items():
                samples, errors = parse_payload(
                    orjson.dumps(rows),
                    content_type="application/json",
                    now_ms=now_ms,
                    max_bytes=s.max_payload_bytes,
                    max_samples=s.max_samples_per_payload,
                    max_future_ms=int(s.max_future_s * 1000),
                    vehicle_id=vehicle_id,
                )
                rejected += len(errors)
                sent += len(rows)
                futures.append(service.ingest.submit(vehicle_id, samples, len(samples) + len(errors)))
            while reports and reports[0][0] < t_end:  # as the HTTP route does: parse, then store and fan out
                _, report = reports.pop(0)
                service.station_reports(
                    parse_reports(orjson.dumps(report), station_id=report["station_id"], now_ms=int(time.time() * 1000))
                )
                station_sent += 1
            while instants and t_end >= instants[0]:
                _wait_idle(service)
                instant = instants.pop(0)
                snapshots[instant] = service.friction_map.cells(drives.start_ms + int(instant * 1000))
            if service.ingest.backlog > max_backlog:  # backpressure, as the MQTT side does
                while service.ingest.backlog > max_backlog // 2:
                    time.sleep(WAIT_STEP_S)
            if len(futures) > 1000:
                futures = [f for f in futures if not f.done() or f.exception() is not None]
            if progress is not None:
                progress(t_end)
        if edge is not None:
            edge.finish(service)
            rejected += edge.rejected
        _wait_idle(service)
        for instant in instants:
            snapshots[instant] = service.friction_map.cells(drives.start_ms + int(instant * 1000))
        failed = [f.exception() for f in futures if f.done() and f.exception() is not None]
        if failed:
            raise RuntimeError(f"{len(failed)} submissions failed, the first: {failed[0]!r}")
        stats = service.ingest.stats()
    # the service stopped: every round stored; read what it decided
    storage_settings = Settings(data_dir=data_dir, mqtt="off", map_clock="data", admin_secret="fleet-benchmark-admin")
    from roadgrip.cloud.storage.database import open_storage

    storage = open_storage(storage_settings.storage_url)
    try:
        warnings = storage.warnings(active_only=False)
    finally:
        storage.close()
    return ServiceRun(
        warnings,
        snapshots,
        sent,
        rejected,
        stats,
        time.perf_counter() - started,
        recorder.table(),
        recorder.station_table(),
        station_sent,
        tuple(stations),
    )


# --------------------------------------------------------------------------------------------------- truth
def patch_cells(network: Network, patch: Patch, resolution: int = 10, step_m: float = 1.0) -> set[str]:
    """The H3 cells of the road points (every `step_m` along each road) that lie on the patch."""
    cells: set[str] = set()
    for road in network.roads:
        xy = points_at(road.path, np.arange(0.0, road.path.length_m, step_m))
        inside = xy[patch.contains(xy[:, 0], xy[:, 1])]
        if inside.size:
            lat, lon, _ = pymap3d.enu2geodetic(inside[:, 0], inside[:, 1], 0.0, *network.origin, 0.0)
            cells |= {h3.latlng_to_cell(a, b, resolution) for a, b in zip(np.atleast_1d(lat), np.atleast_1d(lon))}
    return cells


def find_passes(
    t_s: np.ndarray,
    vehicle: np.ndarray,
    east_m: np.ndarray,
    north_m: np.ndarray,
    mu: np.ndarray,
    patch: Patch,
    gap_s: float = 1.0,
    while_there: bool = True,
) -> list[tuple[str, float, float]]:
    """(vehicle_id, entered s, left s) of every pass over the patch while it was there: consecutive samples of a
    vehicle on the patch whose true mu is the patch's (gap_s apart at most). `while_there` False: every pass over its
    place, whatever the road was."""
    on = patch.contains(east_m, north_m)
    if while_there:
        on &= np.isclose(mu, patch.mu, atol=1e-6)
    idx = np.flatnonzero(on)
    passes = []
    by_vehicle: dict[str, list[float]] = {}
    for i in idx.tolist():
        by_vehicle.setdefault(vehicle[i], []).append(float(t_s[i]))
    for vehicle_id, times in by_vehicle.items():
        times.sort()
        first = last = times[0]
        for t in times[1:]:
            if t - last > gap_s:
                passes.append((vehicle_id, first, last))
                first = t
            last = t
        passes.append((vehicle_id, first, last))
    return sorted(passes, key=lambda p: p[1])


def observable(
    drives: Drives, patch: Patch, passes: list[tuple[str, float, float]], min_samples: int = OBSERVABLE_SAMPLES
) -> int:
    """How many of the passes had at least `min_samples` (the benchmark's: OBSERVABLE_SAMPLES) excited samples on the
    patch (the truth's view: a braking or an acceleration that made the patch's mu observable)."""
    on = np.flatnonzero(patch.contains(drives.east_m, drives.north_m) & drives.excited)
    count = 0
    for vehicle_id, first, last in passes:
        sel = on[(drives.vehicle[on] == vehicle_id) & (drives.t_s[on] >= first) & (drives.t_s[on] <= last)]
        count += sel.size >= min_samples
    return count


def truth_by_cell(network: Network, t_s: float, resolution: int = 10, step_m: float = 2.0) -> dict[str, tuple]:
    """cell -> (lowest, highest) true mu over the road points in the cell at time t_s."""
    out: dict[str, list] = {}
    for road in network.roads:
        xy = points_at(road.path, np.arange(0.0, road.path.length_m, step_m))
        mu = np.full(len(xy), network.dry_mu)
        for patch in network.patches:
            if patch.active(t_s):
                inside = patch.contains(xy[:, 0], xy[:, 1])
                mu[inside] = np.minimum(mu[inside], patch.mu)
        lat, lon, _ = pymap3d.enu2geodetic(xy[:, 0], xy[:, 1], 0.0, *network.origin, 0.0)
        for a, b, m in zip(lat.tolist(), lon.tolist(), mu.tolist()):
            cell = h3.latlng_to_cell(a, b, resolution)
            lo_hi = out.setdefault(cell, [m, m])
            lo_hi[0], lo_hi[1] = min(lo_hi[0], m), max(lo_hi[1], m)
    return {c: tuple(v) for c, v in out.items()}
