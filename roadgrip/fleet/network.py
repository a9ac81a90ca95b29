"""Road networks and slippery patches for the fleet: generated around an origin, or read from GeoJSON.

Coordinates are metres east/north of the network's origin (the simulator's frame; `SensorModel` turns them into WGS84
around the same origin). A `Road` is a polyline a vehicle drives from end to end (a route); a `Patch` is a disc of road
surface (wet, snow, ice) whose adhesion replaces the dry road's wherever a road crosses it. A patch may appear and dry
up during a run (`appear_s`, `dry_s`, seconds on the run's clock; default: there all along): `Network.mu_profile` with
an `arrival_s` clock (station -> the time the vehicle gets there, `roadgrip.fleet.fleet.planned_arrival`) gives a
vehicle the patches that are there when it reaches them. The simulator's mu is a function of the station, so a patch
is judged at the planned arrival; a patch that appears or dries while a vehicle is on it is the patch as it was
when the vehicle reached its first station.

Surface adhesion: the peak of the Burckhardt curve of each surface (roadgrip/vehicle/tires/burckhardt_surfaces.csv, via
roadgrip.vehicle.tires.burckhardt): dry asphalt 1.17, wet asphalt 0.80, snow 0.19, ice 0.05.

GeoJSON (RFC 7946, lon/lat): LineString features are roads (properties: `name`, `kind` in expressway/ramp/urban, and
optional `speed_mps`); Point features with properties `surface` (wet, snow, ice) and `radius_m` are patches (optional: `mu`, `appear_s`,
`dry_s`).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path as FilePath

import numpy as np
import pymap3d

from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.sensors import HEBEI_ORIGIN
from roadgrip.vehicle.tires.burckhardt import SURFACES, peak_mu

SURFACE_MU = {
    "dry": peak_mu(*SURFACES["dry_asphalt"]),
    "wet": peak_mu(*SURFACES["wet_asphalt"]),
    "snow": peak_mu(*SURFACES["snow"]),
    "ice": peak_mu(*SURFACES["ice"]),
}
# Cruising speeds by road kind (m/s): 100 km/h on the expressway, 54 km/h on ramps, 43 km/h in town.
ROAD_SPEED_MPS = {"expressway": 27.8, "ramp": 15.0, "urban": 12.0}
MU_STEP_M = 2.0  # resolution of the mu profile along a road


@dataclass(frozen=True, eq=False)
class Road:
    name: str
    kind: str
    points_m: np.ndarray  # (n, 2) east, north
    speed_mps: float | None = None

    def __post_init__(self):
        if self.kind not in ROAD_SPEED_MPS:
            raise ValueError(f"road {self.name!r}: kind must be one of {sorted(ROAD_SPEED_MPS)}, got {self.kind!r}")
        object.__setattr__(self, "points_m", Path(np.asarray(self.points_m, dtype=np.float64)).points_m)

    @property
    def path(self) -> Path:
        return Path(self.points_m)

    @property
    def cruise_mps(self) -> float:
        return self.speed_mps if self.speed_mps is not None else ROAD_SPEED_MPS[self.kind]

    def reversed(self) -> Road:
        return Road(f"{self.name}-reverse", self.kind, self.points_m[::-1].copy(), self.speed_mps)


@dataclass(frozen=True)
class Patch:
    """A disc of wet, snowy or icy road. Its adhesion is the surface's (SURFACE_MU) unless `mu_value` gives it (slush,
    a worn wet road: a surface between the Burckhardt ones). It is there from `appear_s` until `dry_s` (seconds on
    the run's clock; dry_s excluded)."""

    name: str
    surface: str
    east_m: float
    north_m: float
    radius_m: float
    mu_value: float | None = None
    appear_s: float = 0.0
    dry_s: float = math.inf

    def __post_init__(self):
        if self.surface not in SURFACE_MU or self.surface == "dry":
            raise ValueError(f"patch {self.name!r}: surface must be wet, snow or ice, got {self.surface!r}")
        if not self.radius_m > 0:
            raise ValueError(f"patch {self.name!r}: radius_m must be > 0, got {self.radius_m!r}")
        if self.mu_value is not None and not 0.0 < self.mu_value < SURFACE_MU["dry"]:
            raise ValueError(
                f"patch {self.name!r}: mu_value must lie in (0, {SURFACE_MU['dry']:.2f}) (below the dry "
                f"road), got {self.mu_value!r}"
            )
        if not (math.isfinite(self.appear_s) and self.appear_s < self.dry_s):
            raise ValueError(
                f"patch {self.name!r}: appear_s must be finite and before dry_s, got appear_s "
                f"{self.appear_s!r}, dry_s {self.dry_s!r}"
            )

    @property
    def mu(self) -> float:
        return SURFACE_MU[self.surface] if self.mu_value is None else self.mu_value

    def active(self, t_s) -> np.ndarray | bool:
        """Whether the patch is there at time(s) t_s (appear_s <= t < dry_s)."""
        return (np.asarray(t_s) >= self.appear_s) & (np.asarray(t_s) < self.dry_s)

    def contains(self, east_m, north_m) -> np.ndarray:
        """Whether the points lie on the patch (inside its disc)."""
        return np.hypot(np.asarray(east_m) - self.east_m, np.asarray(north_m) - self.north_m) <= self.radius_m


@dataclass(frozen=True)
class Network:
    roads: tuple[Road, ...]
    patches: tuple[Patch, ...] = ()
    origin: tuple[float, float] = HEBEI_ORIGIN
    dry_mu: float = field(default=SURFACE_MU["dry"])

    def mu_profile(self, road: Road, arrival_s: Callable[[np.ndarray], np.ndarray] | None = None) -> MuProfile:
        """The road's adhesion along its stations: dry, except where it crosses a patch (the lowest patch wins).
        Without `arrival_s` every patch counts whatever its times; with it (stations in m -> the times in s the vehicle
        reaches them) a patch counts where it is there when the vehicle reaches its first station on the road."""
        path = road.path
        stations = np.arange(0.0, path.length_m, MU_STEP_M)
        xy = points_at(path, stations)
        mu = np.full(stations.size, self.dry_mu)
        for patch in self.patches:
            inside = patch.contains(xy[:, 0], xy[:, 1])
            if arrival_s is not None and inside.any():
                first = stations[np.flatnonzero(inside)[0]]
                if not patch.active(float(np.asarray(arrival_s(np.array([first])))[0])):
                    continue
            mu[inside] = np.minimum(mu[inside], patch.mu)
        change = np.concatenate([[True], mu[1:] != mu[:-1]])
        return MuProfile(stations[change], mu[change], mu[change], "step")

    def patch_stations(self, road: Road) -> list[tuple[float, float, Patch]]:
        """(first, last station in m, patch) for each patch the road crosses."""
        path = road.path
        stations = np.arange(0.0, path.length_m, MU_STEP_M)
        xy = points_at(path, stations)
        found = []
        for patch in self.patches:
            inside = np.flatnonzero(patch.contains(xy[:, 0], xy[:, 1]))
            if inside.size:
                found.append((float(stations[inside[0]]), float(stations[inside[-1]]), patch))
        return found


def points_at(path: Path, stations_m: np.ndarray) -> np.ndarray:
    """Points (east, north) of the path at the given stations (linear along each segment)."""
    s = path.stations_m
    return np.column_stack(
        [np.interp(stations_m, s, path.points_m[:, 0]), np.interp(stations_m, s, path.points_m[:, 1])]
    )


def _arc(start: np.ndarray, heading_rad: float, radius_m: float, angle_rad: float, step_m: float = 5.0) -> np.ndarray:
    """Points of a circular arc from `start` heading `heading_rad`, turning left for a positive angle."""
    n = max(2, int(abs(angle_rad) * radius_m / step_m))
    theta = np.linspace(0.0, angle_rad, n + 1)
    side = math.copysign(1.0, angle_rad)
    centre = start + side * radius_m * np.array([-math.sin(heading_rad), math.cos(heading_rad)])
    phi = heading_rad - side * math.pi / 2 + theta
    return centre + radius_m * np.column_stack([np.cos(phi), np.sin(phi)])


def generated_network(origin: tuple[float, float] = HEBEI_ORIGIN) -> Network:
    """A small network around `origin`: a 5 km expressway (two gentle curves of 1.5 km radius), an on-ramp joining it
    and an urban grid (streets 300 m apart, avenues 600 m) south of it, with an icy patch on the expressway 1.5 km from
    its start, a snowy one on the ramp and a wet one in town."""
    straight1 = np.column_stack([np.linspace(-2500.0, -500.0, 41), np.zeros(41)])
    curve1 = _arc(straight1[-1], 0.0, 1500.0, math.radians(12.0))[1:]
    heading = math.radians(12.0)
    tail = curve1[-1] + np.outer(np.linspace(25.0, 1000.0, 40), [math.cos(heading), math.sin(heading)])
    curve2 = _arc(tail[-1], heading, 1500.0, -math.radians(12.0))[1:]
    last = curve2[-1] + np.outer(np.linspace(25.0, 1200.0, 48), [1.0, 0.0])
    expressway = np.vstack([straight1, curve1, tail, curve2, last])
    # on-ramp: 300 m east, then a quarter circle of 400 m radius up to the expressway at (-1100, 0)
    ramp = np.vstack(
        [
            np.column_stack([np.linspace(-1800.0, -1500.0, 13), np.full(13, -400.0)]),
            _arc(np.array([-1500.0, -400.0]), 0.0, 400.0, math.pi / 2)[1:],
        ]
    )
    urban = []
    for k, north in enumerate((-700.0, -1000.0, -1300.0)):
        xs = np.linspace(-2000.0, 0.0, 81)
        urban.append(Road(f"street-{k + 1}", "urban", np.column_stack([xs, np.full(xs.size, north)])))
    for k, east in enumerate((-1700.0, -1100.0, -500.0)):
        ys = np.linspace(-600.0, -1400.0, 33)
        urban.append(Road(f"avenue-{k + 1}", "urban", np.column_stack([np.full(ys.size, east), ys])))
    roads = (Road("expressway-east", "expressway", expressway), Road("on-ramp", "ramp", ramp), *urban)
    patches = (
        Patch("ice-expressway", "ice", -1000.0, 0.0, 60.0),
        Patch("snow-ramp", "snow", float(ramp[len(ramp) // 2, 0]), float(ramp[len(ramp) // 2, 1]), 40.0),
        Patch("wet-town", "wet", -1100.0, -1000.0, 80.0),
    )
    return Network(roads, patches, origin)


def network_from_geojson(path: str | FilePath, origin: tuple[float, float] | None = None) -> Network:
    """Roads (LineString) and patches (Point with surface and radius_m) of a GeoJSON FeatureCollection; the origin
    defaults to the first road's first point."""
    data = json.loads(FilePath(path).read_text())
    if data.get("type") != "FeatureCollection":
        raise ValueError(f"{path}: a GeoJSON FeatureCollection is needed, got type {data.get('type')!r}")
    features = data.get("features", [])
    lines = [f for f in features if f.get("geometry", {}).get("type") == "LineString"]
    if not lines:
        raise ValueError(f"{path}: no LineString feature (a road) in the collection")
    if origin is None:
        lon, lat = lines[0]["geometry"]["coordinates"][0][:2]
        origin = (lat, lon)

    def enu(coordinates) -> np.ndarray:
        lon, lat = np.asarray(coordinates, dtype=np.float64)[:, :2].T
        east, north, _ = pymap3d.geodetic2enu(lat, lon, np.zeros(lat.size), origin[0], origin[1], 0.0)
        return np.column_stack([east, north])

    roads, patches = [], []
    for k, feature in enumerate(lines):
        props = feature.get("properties") or {}
        roads.append(
            Road(
                str(props.get("name", f"road-{k + 1}")),
                str(props.get("kind", "urban")),
                enu(feature["geometry"]["coordinates"]),
                props.get("speed_mps"),
            )
        )
    for k, feature in enumerate(f for f in features if f.get("geometry", {}).get("type") == "Point"):
        props = feature.get("properties") or {}
        east, north = enu([feature["geometry"]["coordinates"]])[0]
        patches.append(
            Patch(
                str(props.get("name", f"patch-{k + 1}")),
                str(props.get("surface")),
                float(east),
                float(north),
                float(props.get("radius_m", 50.0)),
                props.get("mu"),
                float(props.get("appear_s", 0.0)),
                float(props.get("dry_s", math.inf)),
            )
        )
    return Network(tuple(roads), tuple(patches), origin)
