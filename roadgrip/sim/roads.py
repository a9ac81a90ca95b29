"""Roads: the path a vehicle follows (any polyline; straight and circular ones built for you), the road's adhesion
coefficient along it, which may differ between the left and right wheel tracks and vary along the road in steps or ramps,
and the road's longitudinal grade along it.

All are tables the compiled simulator reads: a path as rows (x_m, y_m, station_m), a mu profile as rows
(station_m, mu_left, mu_right) with an interpolation mode, a grade profile as rows (station_m, grade_rad).

The path is the road's plan view unrolled: on a grade the simulator moves the car along it at its speed, so x_m and y_m are
distances along the road (cos(grade) of them horizontal: 0.998 at 6 %).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

MU_MAX = 1.5  # the highest adhesion coefficient a road may be given (dry asphalt with racing tires reaches ~1.3)
MU_MODES = {"step": 0, "linear": 1}
GRADE_MAX_RAD = 0.3  # 31 %: steeper than any public road (the steepest streets are about 35 %, motorways at most 6-7 %)


@dataclass(frozen=True, eq=False)
class Path:
    """A polyline path in the road's local east/north frame (m); the vehicle starts at its first point, heading along it."""

    points_m: np.ndarray  # (n, 2)

    def __post_init__(self):
        pts = np.asarray(self.points_m, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 2 or pts.shape[0] < 2:
            raise ValueError(f"Path.points_m must have shape (n >= 2, 2), got {pts.shape}")
        if not np.isfinite(pts).all():
            raise ValueError("Path.points_m must be finite")
        seg = np.hypot(*np.diff(pts, axis=0).T)
        if (seg <= 1e-6).any():
            raise ValueError(f"Path.points_m has a zero-length segment at index {int(np.argmax(seg <= 1e-6))}")
        object.__setattr__(self, "points_m", pts)

    @property
    def stations_m(self) -> np.ndarray:
        return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.points_m, axis=0).T))])

    @property
    def length_m(self) -> float:
        return float(self.stations_m[-1])

    def table(self) -> np.ndarray:
        """Rows (x_m, y_m, station_m) for the compiled simulator."""
        return np.column_stack([self.points_m, self.stations_m])

    @classmethod
    def straight(cls, length_m: float, heading_rad: float = 0.0) -> Path:
        if not length_m > 0:
            raise ValueError(f"straight road length_m must be > 0, got {length_m!r}")
        return cls(np.array([[0.0, 0.0], [length_m * math.cos(heading_rad), length_m * math.sin(heading_rad)]]))

    @classmethod
    def circle(cls, radius_m: float, arc_length_m: float, segment_m: float = 2.0, left: bool = True) -> Path:
        """An arc of a circle starting at the origin heading east, turning left (or right) with the given radius."""
        if not radius_m > 0:
            raise ValueError(f"circular road radius_m must be > 0, got {radius_m!r}")
        if not arc_length_m > 0:
            raise ValueError(f"circular road arc_length_m must be > 0, got {arc_length_m!r}")
        n = max(math.ceil(arc_length_m / segment_m), 2)
        theta = np.linspace(0.0, arc_length_m / radius_m, n + 1)
        side = 1.0 if left else -1.0
        return cls(np.column_stack([radius_m * np.sin(theta), side * radius_m * (1.0 - np.cos(theta))]))

    @classmethod
    def lane_changes(
        cls, length_m: float, starts_m, offsets_m, transition_m: float = 40.0, step_m: float = 2.0
    ) -> Path:
        """A straight road along x with smooth (cosine) lateral moves to offsets_m[k] beginning at starts_m[k]."""
        x = np.arange(0.0, length_m + step_m, step_m)
        y = np.zeros_like(x)
        previous = 0.0
        for start, offset in sorted(zip(starts_m, offsets_m)):
            u = np.clip((x - start) / transition_m, 0.0, 1.0)
            y = np.where(x >= start, previous + (offset - previous) * 0.5 * (1.0 - np.cos(math.pi * u)), y)
            previous = offset
        return cls(np.column_stack([x, y]))


@dataclass(frozen=True, eq=False)
class MuProfile:
    """Road adhesion coefficient along the path: values at stations (m), per wheel track (left, right).

    'step': the value at station s_k holds until s_{k+1}; 'linear': linear between stations. Before the first station the
    first value holds, after the last the last value."""

    stations_m: np.ndarray
    mu_left: np.ndarray
    mu_right: np.ndarray
    mode: str = "step"

    def __post_init__(self):
        arrays = [
            np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in (self.stations_m, self.mu_left, self.mu_right)
        ]
        for name, a in zip(("stations_m", "mu_left", "mu_right"), arrays):
            if a.ndim != 1 or a.size != arrays[0].size:
                raise ValueError(f"MuProfile.{name} must be 1-D with {arrays[0].size} values, got shape {a.shape}")
            if not np.isfinite(a).all():
                raise ValueError(f"MuProfile.{name} must be finite, got {a.tolist()}")
        for name, a in zip(("mu_left", "mu_right"), arrays[1:]):
            bad = a[(a < 0.0) | (a > MU_MAX)]
            if bad.size:
                raise ValueError(f"MuProfile.{name} must lie in [0, {MU_MAX}], got {float(bad[0])!r}")
        if (np.diff(arrays[0]) <= 0).any():
            raise ValueError(f"MuProfile.stations_m must increase strictly, got {arrays[0].tolist()}")
        if self.mode not in MU_MODES:
            raise ValueError(f"MuProfile.mode must be one of {sorted(MU_MODES)}, got {self.mode!r}")
        for name, a in zip(("stations_m", "mu_left", "mu_right"), arrays):
            object.__setattr__(self, name, a)

    @classmethod
    def uniform(cls, mu: float) -> MuProfile:
        return cls([0.0], [mu], [mu])

    @classmethod
    def sections(cls, values, section_length_m: float) -> MuProfile:
        """Equal-length sections with a step between them (the paper's increasing and decreasing roads)."""
        if not section_length_m > 0:
            raise ValueError(f"MuProfile section_length_m must be > 0, got {section_length_m!r}")
        stations = section_length_m * np.arange(len(values))
        return cls(stations, values, values)

    def table(self) -> np.ndarray:
        """Rows (station_m, mu_left, mu_right) for the compiled simulator."""
        return np.column_stack([self.stations_m, self.mu_left, self.mu_right])

    def at(self, station_m, left: bool = True) -> np.ndarray:
        """mu at the given stations (numpy; the same rule as the compiled `mu_at`)."""
        station = np.atleast_1d(np.asarray(station_m, dtype=np.float64))
        table = self.table()
        return np.array([mu_at(table, table.shape[0], MU_MODES[self.mode], s, 1 if left else 2) for s in station])


@dataclass(frozen=True, eq=False)
class GradeProfile:
    """Longitudinal road grade along the path: angle (rad, positive uphill in the direction of travel) at stations (m),
    linear between them (a vertical curve), the first value before the first station and the last after the last."""

    stations_m: np.ndarray
    grade_rad: np.ndarray

    def __post_init__(self):
        stations = np.atleast_1d(np.asarray(self.stations_m, dtype=np.float64))
        grade = np.atleast_1d(np.asarray(self.grade_rad, dtype=np.float64))
        if stations.ndim != 1 or grade.shape != stations.shape or stations.size < 1:
            raise ValueError(
                f"GradeProfile needs stations_m and grade_rad of one length >= 1, got {stations.shape} and "
                f"{grade.shape}"
            )
        if not (np.isfinite(stations).all() and np.isfinite(grade).all()):
            raise ValueError("GradeProfile stations_m and grade_rad must be finite")
        if (np.diff(stations) <= 0).any():
            raise ValueError(f"GradeProfile.stations_m must increase strictly, got {stations.tolist()}")
        bad = grade[np.abs(grade) > GRADE_MAX_RAD]
        if bad.size:
            raise ValueError(
                f"GradeProfile.grade_rad must lie in [-{GRADE_MAX_RAD}, {GRADE_MAX_RAD}], got {float(bad[0])!r}"
            )
        object.__setattr__(self, "stations_m", stations)
        object.__setattr__(self, "grade_rad", grade)

    @classmethod
    def flat(cls) -> GradeProfile:
        return cls([0.0], [0.0])

    @classmethod
    def uniform(cls, grade_rad: float) -> GradeProfile:
        return cls([0.0], [grade_rad])

    @property
    def is_flat(self) -> bool:
        return bool((self.grade_rad == 0.0).all())

    def table(self) -> np.ndarray:
        """Rows (station_m, grade_rad) for the compiled simulator."""
        return np.column_stack([self.stations_m, self.grade_rad])

    def at(self, station_m) -> np.ndarray:
        return np.interp(np.asarray(station_m, dtype=np.float64), self.stations_m, self.grade_rad)


@njit(cache=True)
def grade_at(table, n, station_m):
    """Grade (rad) at a station from a (station, grade) table: linear between rows, constant beyond the ends."""
    if station_m <= table[0, 0] or n == 1:
        return table[0, 1]
    if station_m >= table[n - 1, 0]:
        return table[n - 1, 1]
    k = 0
    while table[k + 1, 0] <= station_m:
        k += 1
    u = (station_m - table[k, 0]) / (table[k + 1, 0] - table[k, 0])
    return table[k, 1] + u * (table[k + 1, 1] - table[k, 1])


@njit(cache=True)
def mu_at(table, n, mode, station_m, column):
    """mu at a station from a (station, left, right) table; column 1 = left track, 2 = right track."""
    if station_m <= table[0, 0] or n == 1:
        return table[0, column]
    if station_m >= table[n - 1, 0]:
        return table[n - 1, column]
    k = 0
    while table[k + 1, 0] <= station_m:
        k += 1
    if mode == 0:
        return table[k, column]
    u = (station_m - table[k, 0]) / (table[k + 1, 0] - table[k, 0])
    return table[k, column] + u * (table[k + 1, column] - table[k, column])


@njit(cache=True)
def project_on_path(path, n, seg, px, py):
    """Nearest point of the polyline to (px, py), searched from segment `seg` onwards or backwards.

    Returns (segment, station_m, lateral_offset_m): stations extrapolate before the start and past the end; the lateral
    offset is positive to the left of the path."""
    moved = False
    while True:
        dx = path[seg + 1, 0] - path[seg, 0]
        dy = path[seg + 1, 1] - path[seg, 1]
        u = ((px - path[seg, 0]) * dx + (py - path[seg, 1]) * dy) / (dx * dx + dy * dy)
        if u > 1.0 and seg < n - 2:
            seg += 1
            moved = True
        elif u < 0.0 and seg > 0 and not moved:
            seg -= 1
        else:
            break
    length = (dx * dx + dy * dy) ** 0.5
    lateral = (dx * (py - path[seg, 1]) - dy * (px - path[seg, 0])) / length
    return seg, path[seg, 2] + u * length, lateral


@njit(cache=True)
def point_at_station(path, n, seg, station_m):
    """(x, y) of the path at a station at or after segment `seg` (extrapolating past the end)."""
    k = seg
    while k < n - 2 and path[k + 1, 2] < station_m:
        k += 1
    u = (station_m - path[k, 2]) / (path[k + 1, 2] - path[k, 2])
    return path[k, 0] + u * (path[k + 1, 0] - path[k, 0]), path[k, 1] + u * (path[k + 1, 1] - path[k, 1])
