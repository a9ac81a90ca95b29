"""The road-friction map (DESIGN 3.6): estimates (DESIGN 3.4) aggregated per H3 cell, weighted by confidence, fading with age.

Pure and in memory: `add` takes estimate rows (dicts with vehicle_id, timestamp_ms, latitude_deg, longitude_deg, mu,
mu_lower, mu_upper, excited); `cells(now_ms)` summarises every cell with evidence younger than `max_age_s`. Rows without a
position (latitude_deg or longitude_deg None) are ignored.

Weight of an excited estimate i seen at time now (t in ms, the estimate's own timestamp_ms):

    w_i = c_i * 2^(-age_i / half_life),   c_i = 1 / max(mu_upper_i - mu_lower_i, min_interval_width)^2,
    age_i = max(0, now - t_i)

- Confidence c_i: the inverse squared width of the 90 % interval, i.e. inverse variance if the error were Gaussian
  (width = 3.29 sigma), the textbook weight for averaging measurements of one quantity.
- Width floor `min_interval_width` (default 0.2): without it one sample that claims a very narrow interval outweighs
  hundreds of honest ones. The filters report 0.07 wide intervals after an ABS stop while their RMSE over excited
  samples is about 0.14 (docs/ESTIMATORS.md, paper preset), so a 90 % interval narrower than +-0.1 claims more than any
  estimator here has shown. With the floor, one sample weighs at most 25, four times a typical 0.4 wide one.
- Fade 2^(-age / half_life): an estimate half_life_s old weighs half as much as a fresh one. Roads change (rain,
  freezing, salting) over tens of minutes; half_life_s = 600 s by default.
- Non-excited estimates carry no weight for mu (the manoeuvre did not make mu observable; their interval is the prior's).
  They count in n_estimates, n_vehicles and last_ms: the road was driven, we just could not tell its grip.
- "Recent" excited evidence is excited evidence at most max_age_s old. A cell without it has status
  "no_recent_excited_evidence" and mu, mu_lower, mu_upper None.

Cell values, with W = sum w_i (all sums over excited estimates):

    mu = sum w_i mu_i / W
    lo_bar = sum w_i mu_lower_i / W,   hi_bar = sum w_i mu_upper_i / W          (the typical sample's interval)
    s_b^2 = sum w_i mu_i^2 / W - mu^2                                           (spread of the estimates themselves)
    mu_lower = max(0, mu - sqrt((mu - lo_bar)^2 + (1.645 s_b)^2))
    mu_upper = mu + sqrt((hi_bar - mu)^2 + (1.645 s_b)^2)

Why this interval: the estimates of one cell are far from independent (one vehicle's samples share its estimator's bias,
its tires, its vehicle profile), so combining them as independent measurements (width shrinking as 1/sqrt(n)) would give
an interval far narrower than the truth supports. The weighted mean of the bounds is what a typical sample honestly
claims, and keeps the estimator's asymmetry. When the samples disagree (a cell across the edge of an icy patch, or a road
that changed within the window) the mean of the bounds could cover neither surface, so the weighted spread of the point
estimates is added in quadrature on each side (1.645: the 90 % point of a normal). When the samples agree, the interval
is the weighted mean of their bounds; a single estimate gives back its own interval.

Storage (so that `add` is O(rows) and `cells` O(cells), for ~10,000 estimates per second): no estimate is kept. Each
cell holds running sums per time bucket of bucket_s = max_age_s / 6 (keyed by timestamp_ms // bucket_ms). A bucket's
sums are anchored at a reference time, its newest excited timestamp: an estimate adds c_i 2^((t_i - ref) / half_life)
(<= c_i), and a newer one first re-anchors the sums (multiplies them by 2^((ref - t_new) / half_life)) so that no
exponent is ever positive. At `cells(now)` each bucket's sums are multiplied by 2^((ref - now) / half_life): the fade is
applied lazily and exactly. Evidence older than max_age_s is dropped bucket by bucket: a bucket leaves when its newest
estimate is older than max_age_s, so an estimate counts for at least max_age_s and at most max_age_s + bucket_s (by then
it weighs at most 2^(-max_age_s / half_life) = 1/64 of a fresh one with the defaults). `prune` frees such buckets and
cells; `add` calls it once per bucket_s of clock.

Time: ages use the caller's now_ms. If now_ms precedes a cell's newest estimate (a terminal's clock ahead of the
server's), ages in that cell are taken from its newest estimate instead, so that no age is negative: mu and the interval
are ratios and do not change, only `weight` is evaluated at that later instant.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import h3

from roadgrip.cloud.exports import geojson

Z90 = 1.6448536269514722  # standard normal 95 % quantile: a central 90 % interval is +- Z90 sigma
BUCKETS_PER_MAX_AGE = 6  # time buckets per max_age_s: memory per cell against how long old evidence lingers
MEASURED = "measured"
NO_RECENT_EXCITED = "no_recent_excited_evidence"

# layout of a bucket (a list, for speed): anchor of the sums, the weighted sums, counts, newest timestamps
_REF, _W, _WMU, _WMU2, _WLO, _WHI, _N, _NEXC, _LAST, _LASTEXC = range(10)


@dataclass(frozen=True)
class CellSummary:
    """One cell of the map at an instant. mu and its 90 % interval are None without recent excited evidence."""

    cell: str
    latitude_deg: float  # cell centre, WGS84
    longitude_deg: float
    mu: float | None
    mu_lower: float | None
    mu_upper: float | None
    weight: float  # total effective weight now, sum of w_i (1/mu^2 units)
    n_estimates: int  # estimates in the window, excited or not
    n_excited: int
    n_vehicles: int  # distinct vehicles with an estimate in the window
    last_ms: int  # newest estimate, ms since the Unix epoch
    last_excited_ms: int | None
    status: str  # "measured" or "no_recent_excited_evidence"


class _Cell:
    __slots__ = ("buckets", "last_ms", "latitude_deg", "longitude_deg", "vehicles")

    def __init__(self, cell: str):
        self.latitude_deg, self.longitude_deg = h3.cell_to_latlng(cell)
        self.buckets: dict[int, list] = {}
        self.vehicles: dict[str, int] = {}  # vehicle_id -> its newest timestamp_ms in this cell
        self.last_ms = -(2**62)


def _positive_finite(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")
    return float(value)


def validate_resolution(resolution) -> int:
    if isinstance(resolution, bool) or not isinstance(resolution, int) or not 0 <= resolution <= 15:
        raise ValueError(f"resolution must be an integer H3 resolution in 0..15, got {resolution!r}")
    return resolution


class FrictionMap:
    """Per-H3-cell friction from estimate rows; see the module docstring for the weighting and the interval."""

    def __init__(self, resolution: int = 10, half_life_s: float = 600.0, max_age_s: float = 3600.0,
                 min_interval_width: float = 0.2):
        self.resolution = validate_resolution(resolution)
        self.half_life_s = _positive_finite("half_life_s", half_life_s)
        self.max_age_s = _positive_finite("max_age_s", max_age_s)
        self.min_interval_width = _positive_finite("min_interval_width", min_interval_width)
        self.cells_by_id_: dict[str, _Cell] = {}
        self.newest_ms_: int | None = None  # newest timestamp_ms seen: the pruning clock when add() gets no now_ms
        self.last_prune_ms_: int = -(2**62)

    @property
    def bucket_ms(self) -> int:
        return max(1, int(self.max_age_s * 1000.0 / BUCKETS_PER_MAX_AGE))

    def cell_of(self, latitude_deg: float, longitude_deg: float) -> str:
        return h3.latlng_to_cell(latitude_deg, longitude_deg, self.resolution)

    def add(self, estimates: Iterable[dict], now_ms: int | None = None) -> set[str]:
        """Fold estimate rows into the map; the cells touched. `now_ms` (the service's clock) drives pruning; without
        it the newest timestamp seen does, which a terminal with its clock far ahead could push forward."""
        half_life_ms = self.half_life_s * 1000.0
        floor = self.min_interval_width
        bucket_ms = self.bucket_ms
        resolution = self.resolution
        cells = self.cells_by_id_
        to_cell = h3.latlng_to_cell
        isfinite = math.isfinite
        touched: set[str] = set()
        newest = self.newest_ms_ if self.newest_ms_ is not None else -(2**62)
        for row in estimates:
            lat = row["latitude_deg"]
            lon = row["longitude_deg"]
            if lat is None or lon is None:
                continue
            t = int(row["timestamp_ms"])
            cell_id = to_cell(lat, lon, resolution)
            cell = cells.get(cell_id)
            if cell is None:
                cell = cells[cell_id] = _Cell(cell_id)
            key = t // bucket_ms
            b = cell.buckets.get(key)
            if b is None:
                b = cell.buckets[key] = [t, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0, t, None]
            if row["excited"]:
                mu, lo, hi = row["mu"], row["mu_lower"], row["mu_upper"]
                if not (isfinite(mu) and isfinite(lo) and isfinite(hi)) or lo > hi:
                    raise ValueError(f"estimate of vehicle {row['vehicle_id']!r} at {t}: mu {mu!r}, mu_lower {lo!r}, "
                                     f"mu_upper {hi!r} must be finite with mu_lower <= mu_upper")
                width = hi - lo
                width = max(width, floor)
                c = 1.0 / (width * width)  # confidence: inverse squared interval width
                ref = b[_REF]
                if t > ref or b[_W] == 0.0:
                    scale = 2.0 ** ((ref - t) / half_life_ms)  # re-anchor at the newest: sums *= 2^-(t - ref)/h
                    b[_W] *= scale
                    b[_WMU] *= scale
                    b[_WMU2] *= scale
                    b[_WLO] *= scale
                    b[_WHI] *= scale
                    b[_REF] = t
                    f = c
                else:
                    f = c * 2.0 ** ((t - ref) / half_life_ms)  # w = c 2^-(ref - t)/h, relative to the anchor
                b[_W] += f
                b[_WMU] += f * mu
                b[_WMU2] += f * mu * mu
                b[_WLO] += f * lo
                b[_WHI] += f * hi
                b[_NEXC] += 1
                if b[_LASTEXC] is None or t > b[_LASTEXC]:
                    b[_LASTEXC] = t
            b[_N] += 1
            b[_LAST] = max(b[_LAST], t)
            vehicle = row["vehicle_id"]
            if cell.vehicles.get(vehicle, -(2**62)) < t:
                cell.vehicles[vehicle] = t
            cell.last_ms = max(cell.last_ms, t)
            newest = max(newest, t)
            touched.add(cell_id)
        if newest > -(2**62):
            self.newest_ms_ = newest
        clock = now_ms if now_ms is not None else self.newest_ms_
        if clock is not None and clock - self.last_prune_ms_ >= bucket_ms:
            self.prune(clock)
        return touched

    def prune(self, now_ms: int) -> int:
        """Free the buckets, vehicles and cells whose newest estimate is older than max_age_s; the cells removed."""
        max_age_ms = self.max_age_s * 1000.0
        removed = []
        for cell_id, cell in self.cells_by_id_.items():
            for key in [k for k, b in cell.buckets.items() if now_ms - b[_LAST] > max_age_ms]:
                del cell.buckets[key]
            for vehicle in [v for v, t in cell.vehicles.items() if now_ms - t > max_age_ms]:
                del cell.vehicles[vehicle]
            if not cell.buckets:
                removed.append(cell_id)
        for cell_id in removed:
            del self.cells_by_id_[cell_id]
        self.last_prune_ms_ = now_ms
        return len(removed)

    def cells(self, now_ms: int) -> list[CellSummary]:
        """Every cell with an estimate at most max_age_s old at now_ms, ordered by cell id."""
        half_life_ms = self.half_life_s * 1000.0
        max_age_ms = self.max_age_s * 1000.0
        out = []
        for cell_id in sorted(self.cells_by_id_):
            cell = self.cells_by_id_[cell_id]
            if now_ms - cell.last_ms > max_age_ms:
                continue
            t_now = max(cell.last_ms, now_ms)  # ages never negative
            w = wmu = wmu2 = wlo = whi = 0.0
            n = n_excited = 0
            last_excited = None
            for b in cell.buckets.values():
                if now_ms - b[_LAST] > max_age_ms:
                    continue  # the whole bucket is older than max_age_s
                n += b[_N]
                n_excited += b[_NEXC]
                if b[_LASTEXC] is not None and (last_excited is None or b[_LASTEXC] > last_excited):
                    last_excited = b[_LASTEXC]
                if b[_W] > 0.0:
                    fade = 2.0 ** ((b[_REF] - t_now) / half_life_ms)  # lazy decay from the anchor to now
                    w += b[_W] * fade
                    wmu += b[_WMU] * fade
                    wmu2 += b[_WMU2] * fade
                    wlo += b[_WLO] * fade
                    whi += b[_WHI] * fade
            n_vehicles = sum(1 for t in cell.vehicles.values() if now_ms - t <= max_age_ms)
            recent = last_excited is not None and now_ms - last_excited <= max_age_ms and w > 0.0
            if recent:
                mu = wmu / w
                spread = Z90 * math.sqrt(max(0.0, wmu2 / w - mu * mu))
                mu_lower = max(0.0, mu - math.hypot(max(0.0, mu - wlo / w), spread))
                mu_upper = mu + math.hypot(max(0.0, whi / w - mu), spread)
            else:
                mu = mu_lower = mu_upper = None
            out.append(CellSummary(
                cell=cell_id, latitude_deg=cell.latitude_deg, longitude_deg=cell.longitude_deg,
                mu=mu, mu_lower=mu_lower, mu_upper=mu_upper, weight=w, n_estimates=n, n_excited=n_excited,
                n_vehicles=n_vehicles, last_ms=cell.last_ms, last_excited_ms=last_excited,
                status=MEASURED if recent else NO_RECENT_EXCITED))
        return out

    def to_geojson(self, now_ms: int) -> dict:
        """The cells at now_ms as a GeoJSON FeatureCollection (roadgrip.cloud.exports.geojson)."""
        return geojson(self.cells(now_ms))

    def clear(self) -> None:
        self.cells_by_id_.clear()
        self.newest_ms_ = None
        self.last_prune_ms_ = -(2**62)
