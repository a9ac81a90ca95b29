"""The road-friction map (CONTRACTS 3.6): per H3 cell, a posterior over mu that fuses what vehicles and roadside stations
prove, aged.

This module owns the map's evidence model, its mu grid (MU_GRID up to MU_MAX), the ageing, the cell summaries and
their states (cluster mode). It borrows the rest of the domain: what a pass is (late rows included) from passes.py, the
warning engine's rule too; the cell of a position from cells.py; its argument checks from checks.py. Rendering the
cells is the formats' (roadgrip/cloud/formats/geojson.py, datex2.py).

What a cell's value means: the friction a vehicle can count on in the cell, that is its lowest. A cell (76 m across at
resolution 10) holds 100 m or more of road; a patch of ice may cover part of it. A low reading proves that a
slippery spot is in the cell, wherever it was taken; a reading of grip proves grip only where that vehicle loaded its
tires. The evidence model below says so (grip_locality), and the fleet benchmark measured why it matters: without it,
calm passes over the dry half of a patch's cells hid the patch (docs/RESULTS.md, "The map").

Pure and in memory: `add` takes estimate rows (CONTRACTS 3.4 dicts with vehicle_id, timestamp_ms, latitude_deg,
longitude_deg, mu, mu_lower, mu_upper, excited and, from a guarded estimator, mu_proven); `add_station` takes roadside
stations' friction evidence (roadgrip/cloud/domain/stations.py); `cells(now_ms)` summarises every cell with evidence younger
than `max_age_s`. Rows without a position are ignored.

Evidence, on a grid of mu (MU_GRID: 0 to MU_MAX = 1.5 in steps of 0.02, the range a road may have; the prior is flat
over it)
- An estimate's 90 % interval [l, u] says "mu is above l" and "mu is below u". Each side is a soft step:

      L_low(mu) = eps + (1 - eps) Phi((mu - l) / s),   L_high(mu) = eps + (1 - eps) Phi((u - mu) / s)

  (eps is eps_low = grip_locality for the lower side, eps_high = outlier_rate for the upper side, below.) Their
  product is a plateau over [l, u]: the map takes what the estimate proves, not its point value. The point value
  inside a wide interval is mostly the estimator's prior (pmf: "mu >= 0.3, most probably 0.8" from a car that only
  proved 0.3); multiplying such points would make the prior look like evidence. The edge s = W / 8 (W = u - l, at
  least min_interval_width = 0.1): a plateau of width W puts about 0.4 s / W = 5 % of its mass beyond each end, so that
  one estimate alone would give back its own 90 % interval if both sides held for the whole cell. The upper side is
  skipped where u is at least the estimators' "nothing known above" end, 1.2 (roadgrip/estimators/guard.py
  PRIOR_UPPER_MU): an interval [0.6, 1.2] says mu >= 0.6, nothing more, and dry asphalt (1.17 in the simulator) must
  stay inside the cell's interval.
- eps_high = outlier_rate (0.005), the chance that a low reading is wrong beyond its interval (a mislocated sample,
  an estimator's model error), keeps the fusion robust: Gaussian tails alone would let one confident, wrong estimate
  veto any number of others (log Phi(-7) = -27); with eps, evidence that disagrees costs at most log(1/eps) = 5.3 a
  pass, so a road that changed (ice that dried) is decided by how many recent passes say which, and a cell split
  between two surfaces shows both in its interval. It costs a single narrow estimate little: eps (1.5 - W) / W of
  extra mass outside (3 % for W = 0.2).
- eps_low = grip_locality (0.5), the chance that the grip a pass proved does not hold for the whole cell: it loaded its
  tires over a few metres of it. A pass proving grip thus halves the odds of lower mu, where a low reading cuts the
  odds of higher mu 200-fold; three passes proving grip make a cell's 5 % quantile reach their bound. Chosen from the
  fleet benchmark's recorded estimates, replayed into the map (0.005, 0.2, 0.3 and 0.5 tried, docs/RESULTS.md): 0.5
  keeps the patches in their cells (90 % coverage of the lowest true mu 0.93-1.00 against 0.20-0.78 with 0.005) for
  some coverage on dry road (0.67 against 0.74 of the measured dry cells); held-out seeds agree
  (results/trials/results/map_replay.py).
- What a pass proves even without excitation (a car cornering at 0.4 g proves mu >= 0.37): the largest mu_proven of
  the pass's estimates, b, as a sharp lower side Phi((mu - b) / proven_sigma) (0.02: the guard's bound already leaves
  two sigma of the accelerometer's noise and bias, roadgrip/estimators/guard.py), with eps_low: it too is grip where
  the vehicle was. Bounds below
  min_proven_mu (0.1) are not counted: a calm pass proves nothing a map reader needs.

Passes: a pass is one vehicle's consecutive estimates in one cell (it ends when the vehicle is seen in another cell or
after pass_gap_s without an estimate there). The rule, late rows included, is roadgrip/cloud/domain/passes.py's, the
warning engine's too: a row too late for its pass (older than the vehicle's newest in another cell, or no newer than
its last closed pass) is dropped and counted in `late_rows_`; the passes idle for pass_gap_s at the clock (add's
now_ms, or the newest timestamp seen) close at every `add`. One vehicle's estimates of one pass share its
estimator's state, tires and bias: they are one piece of evidence, not tens. A pass's log-likelihood is the mean of its
excited estimates' log-likelihoods (a geometric mean of their plateaus) plus its proven bound's. Passes of different
vehicles, and one vehicle's passes on different visits, add up, to a point: they share the estimator's systematic error
on a surface (pmf reads ice of 0.056 as 0.08), so however many agree, the cell claims no more than max_independent (3)
passes would: the summed log-likelihood is scaled by min(1, max_independent / weight), which keeps the proportions of
what the passes say and bounds how sharp it gets.

Ageing: a pass weighs w = 2^(-age / half_life_s) (age from its last estimate; half_life_s = 600 s by default: roads
change with rain, freezing and salting over tens of minutes), its log-likelihood multiplied by w (a tempered
likelihood: old evidence counts as a fraction of a pass); evidence older than max_age_s is dropped. A station's newest
report in a cell replaces its earlier ones there (one station's readings share its sensor's bias) and is aged the same.

Cell values: the posterior p(mu) ~ exp(c (sum_passes w ll_pass + sum_stations w ll_station)) on the grid, c the cap's
scale; mu is its median
(a plateau has no single most probable value), mu_lower and mu_upper its 5 % and 95 % quantiles (linear between grid
points). `weight` is sum w: the effective number of passes and station reports. Status:
- "measured": recent excited estimates or a station report in the cell;
- "bounded": only proven lower bounds (calm passes); mu_lower approaches the largest bound as passes prove it again
  (about three), mu_upper is near the grid's end;
- "no_recent_excited_evidence": the cell was driven but nothing in the window says anything about its mu; mu,
  mu_lower, mu_upper are None.

Storage: no estimate is kept. A vehicle's pass in progress holds the sum of its estimates' log-likelihoods; a finished
pass is folded into its cell's running sums per time bucket (bucket_s = max_age_s / 6, keyed by the pass's last
timestamp // bucket_ms), anchored at the bucket's newest pass time: a later pass first re-anchors the sums (multiplies
them by 2^((ref - t) / half_life)), so that no exponent is ever positive, and `cells(now)` multiplies each bucket by
2^((ref - now) / half_life): the fade is exact and lazy. Passes in progress are counted in `cells` as they stand. A
bucket leaves when its newest pass is older than max_age_s, so evidence counts for at least max_age_s and at most
max_age_s + bucket_s (by then it weighs at most 2^(-max_age_s / half_life) = 1/64). `prune` closes the passes whose
vehicle has been gone for pass_gap_s, frees old buckets and cells, and forgets the last pass of vehicles gone for
max_age_s; `add` calls it once per bucket_s of clock.

Time: ages use the caller's now_ms. If now_ms precedes a cell's newest evidence (a terminal's clock ahead of the
server's), ages in that cell are taken from its newest evidence instead, so that no age is negative.

Size: over 500 lines because about a fifth is the docstring, the evidence model's derivation; the lazy fade and the
bucket layout must be read together.
"""

from __future__ import annotations

import base64
import operator
from collections.abc import Iterable
from dataclasses import dataclass

import h3
import numpy as np
from scipy.special import ndtr

from roadgrip.cloud.domain import checks
from roadgrip.cloud.domain.cells import cell_of, validate_resolution
from roadgrip.cloud.domain.observations import MIN_PROVEN_MU
from roadgrip.cloud.domain.passes import Pass, Passes, in_pass_order
from roadgrip.estimators.guard import PRIOR_UPPER_MU

# The grid's end: the highest mu a road may have (dry asphalt with racing tires reaches about 1.3; the simulator's roads,
# roadgrip/sim/roads.py, stay within it, tests/cloud/domain/test_domain.py). The prior is flat up to it, so a cell
# that only proved grip keeps every value a road can hold inside its interval.
MU_MAX = 1.5
MU_GRID = np.linspace(0.0, MU_MAX, round(MU_MAX / 0.02) + 1)  # the map's mu values, 0.02 apart
EDGE_PER_WIDTH = 0.125  # an interval's soft edge per its width: 0.4 s / W = 5 % of a plateau beyond each end
BUCKETS_PER_MAX_AGE = 6  # time buckets per max_age_s: memory per cell against how long old evidence lingers
QUANTILES = (0.05, 0.5, 0.95)  # mu_lower, mu, mu_upper
MEASURED = "measured"
BOUNDED = "bounded"
NO_RECENT_EXCITED = "no_recent_excited_evidence"
_NEVER = -(2**62)

# layout of a bucket (a list, for speed): anchor, weight sum, log-likelihood sum, passes, excited passes, estimates,
# excited estimates, newest estimate, newest excited estimate, largest proven bound
_REF, _W, _LL, _NPASS, _NPASS_EXC, _N, _NEXC, _LAST, _LASTEXC, _PROVEN = range(10)


@dataclass(frozen=True)
class CellSummary:
    """One cell of the map at an instant. mu and its 90 % interval are None without recent evidence about mu."""

    cell: str
    latitude_deg: float  # cell centre, WGS84
    longitude_deg: float
    mu: float | None  # median of the cell's posterior
    mu_lower: float | None  # its 5 % quantile
    mu_upper: float | None  # its 95 % quantile
    weight: float  # effective number of passes and station reports now (each faded by its age)
    n_estimates: int  # estimates in the window, excited or not
    n_excited: int
    n_vehicles: int  # distinct vehicles with an estimate in the window
    last_ms: int  # newest estimate or station report, ms since the Unix epoch
    last_excited_ms: int | None  # newest excited estimate or station report
    status: str  # "measured", "bounded" or "no_recent_excited_evidence"
    n_passes: int = 0  # vehicle passes in the window
    n_stations: int = 0  # stations with a report in the window
    mu_proven: float | None = None  # the largest lower bound a pass in the window proved (counted ones only)


class _Pass(Pass):
    """A pass (passes.py) as the map keeps it: the sum of its excited estimates' log-likelihoods, its counts, its largest
    proven bound."""

    __slots__ = ("last_exc_ms", "ll", "n", "n_exc", "proven")

    def __init__(self, vehicle_id: str, cell: str, t: int):
        super().__init__(vehicle_id, cell, t)
        self.ll: np.ndarray | None = None  # sum of its excited estimates' log-likelihoods
        self.n = self.n_exc = 0
        self.last_exc_ms: int | None = None
        self.proven = 0.0


class _Cell:
    __slots__ = ("buckets", "last_ms", "latitude_deg", "longitude_deg", "stations", "vehicles")

    def __init__(self, cell: str):
        self.latitude_deg, self.longitude_deg = h3.cell_to_latlng(cell)
        self.buckets: dict[int, list] = {}
        self.vehicles: dict[str, int] = {}  # vehicle_id -> its newest timestamp_ms in this cell
        self.stations: dict[str, tuple[int, np.ndarray]] = {}  # station_id -> (report time, log-likelihood)
        self.last_ms = _NEVER


def _pack(ll: np.ndarray | None) -> str | None:
    return None if ll is None else base64.b64encode(np.asarray(ll, dtype="<f8").tobytes()).decode("ascii")


def _unpack(packed: str | None) -> np.ndarray | None:
    return None if packed is None else np.frombuffer(base64.b64decode(packed), dtype="<f8").astype(np.float64)


def posterior_quantiles(log_posterior: np.ndarray, quantiles=QUANTILES) -> np.ndarray:
    """Quantiles of posteriors given on MU_GRID as log densities (one per row): the cumulative trapezoid of the
    density, inverted linearly between grid points. Shape (rows, len(quantiles))."""
    log_posterior = np.atleast_2d(log_posterior)
    density = np.exp(log_posterior - log_posterior.max(axis=1, keepdims=True))
    step = MU_GRID[1] - MU_GRID[0]
    cdf = np.concatenate(
        [np.zeros((len(density), 1)), np.cumsum(0.5 * (density[:, 1:] + density[:, :-1]) * step, axis=1)], axis=1
    )
    cdf /= cdf[:, -1:]
    return np.array([np.interp(quantiles, row, MU_GRID) for row in cdf])


class FrictionMap:
    """Per-H3-cell friction posteriors from estimate rows and station reports; see the module docstring."""

    def __init__(
        self,
        resolution: int = 10,
        half_life_s: float = 600.0,
        max_age_s: float = 3600.0,
        min_interval_width: float = 0.1,
        outlier_rate: float = 0.005,
        proven_sigma: float = 0.02,
        min_proven_mu: float = MIN_PROVEN_MU,
        pass_gap_s: float = 30.0,
        max_independent: float = 3.0,
        grip_locality: float = 0.5,
    ):
        self.resolution = validate_resolution(resolution)
        self.half_life_s = checks.positive_finite("half_life_s", half_life_s)
        self.max_age_s = checks.positive_finite("max_age_s", max_age_s)
        self.min_interval_width = checks.positive_finite("min_interval_width", min_interval_width)
        self.outlier_rate = checks.probability("outlier_rate", outlier_rate)
        self.proven_sigma = checks.positive_finite("proven_sigma", proven_sigma)
        self.min_proven_mu = checks.positive_finite("min_proven_mu", min_proven_mu)
        self.pass_gap_s = checks.positive_finite("pass_gap_s", pass_gap_s)
        self.max_independent = checks.positive_finite("max_independent", max_independent)
        self.grip_locality = checks.probability("grip_locality", grip_locality)
        self.cells_by_id_: dict[str, _Cell] = {}
        self.passes_ = Passes(self.pass_gap_s, _Pass, self._fold)  # the pass rule (passes.py)
        self.open_passes_: dict[str, _Pass] = self.passes_.open  # vehicle_id -> its pass in progress
        self.newest_ms_: int | None = None  # newest timestamp_ms seen: the pruning clock when add() gets no now_ms
        self.last_prune_ms_: int = _NEVER

    @property
    def late_rows_(self) -> int:
        """Rows dropped as too late for their pass (passes.py, rule 3)."""
        return self.passes_.late_rows

    @property
    def bucket_ms(self) -> int:
        return max(1, int(self.max_age_s * 1000.0 / BUCKETS_PER_MAX_AGE))

    def cell_of(self, latitude_deg: float, longitude_deg: float) -> str:
        """The cell of a position at the map's resolution (cells.py)."""
        return cell_of(latitude_deg, longitude_deg, self.resolution)

    # ------------------------------------------------------------------------------------------------- evidence

    def _soft(self, z: np.ndarray, eps: float | None = None) -> np.ndarray:
        eps = self.outlier_rate if eps is None else eps
        return np.log(eps + (1.0 - eps) * ndtr(z))

    def interval_log_likelihood(self, lower, upper) -> np.ndarray:
        """Log-likelihoods on MU_GRID of intervals [lower, upper] (arrays of n), shape (n, grid): two soft steps."""
        lower = np.asarray(lower, dtype=np.float64)[:, None]
        upper = np.asarray(upper, dtype=np.float64)[:, None]
        edge = EDGE_PER_WIDTH * np.maximum(upper - lower, self.min_interval_width)
        ll = self._soft((MU_GRID - lower) / edge, self.grip_locality)
        return ll + np.where(upper < PRIOR_UPPER_MU, self._soft((upper - MU_GRID) / edge), 0.0)

    def proven_log_likelihood(self, proven: float) -> np.ndarray:
        """Log-likelihood on MU_GRID of "mu >= proven" (a pass's largest bound)."""
        return self._soft((MU_GRID - proven) / self.proven_sigma, self.grip_locality)

    def _pass_log_likelihood(self, p: _Pass) -> np.ndarray | None:
        ll = p.ll / p.n_exc if p.n_exc else None
        if p.proven >= self.min_proven_mu:
            bound = self.proven_log_likelihood(p.proven)
            ll = bound if ll is None else ll + bound
        return ll

    # ------------------------------------------------------------------------------------------------------ add

    def add(self, estimates: Iterable[dict], now_ms: int | None = None) -> set[str]:
        """Fold estimate rows into the map; the cells touched. `now_ms` (the service's clock) drives pruning; without
        it the newest timestamp seen does, which a terminal with its clock far ahead could push forward."""
        resolution = self.resolution
        to_cell = cell_of
        rows = in_pass_order(estimates)
        excited = [r for r in rows if r["excited"]]
        for r in excited:
            checks.interval(
                f"estimate of vehicle {r['vehicle_id']!r} at {r['timestamp_ms']}", r["mu_lower"], r["mu_upper"], r["mu"]
            )
        lls = (
            self.interval_log_likelihood([r["mu_lower"] for r in excited], [r["mu_upper"] for r in excited])
            if excited
            else None
        )
        k = 0
        touched: set[str] = set()
        cells = self.cells_by_id_
        place = self.passes_.row
        newest = self.newest_ms_ if self.newest_ms_ is not None else _NEVER
        for row in rows:
            vehicle = row["vehicle_id"]
            t = int(row["timestamp_ms"])
            p = place(vehicle, to_cell(row["latitude_deg"], row["longitude_deg"], resolution), t)
            if p is None:  # too late for its pass: dropped (passes.py)
                k += row["excited"]  # its log-likelihood was computed with the others'
                continue
            cell_id = p.cell
            p.n += 1
            proven = row.get("mu_proven")
            if proven is not None and proven > p.proven:
                p.proven = float(proven)
            if row["excited"]:
                p.ll = lls[k].copy() if p.ll is None else p.ll + lls[k]
                k += 1
                p.n_exc += 1
                p.last_exc_ms = t if p.last_exc_ms is None else max(p.last_exc_ms, t)
            cell = cells.get(cell_id)
            if cell is None:
                cell = cells[cell_id] = _Cell(cell_id)
            if cell.vehicles.get(vehicle, _NEVER) < t:
                cell.vehicles[vehicle] = t
            cell.last_ms = max(cell.last_ms, t)
            newest = max(newest, t)
            touched.add(cell_id)
        if newest > _NEVER:
            self.newest_ms_ = newest
        clock = now_ms if now_ms is not None else self.newest_ms_
        if clock is not None:
            self.passes_.close_idle(clock)
            if clock - self.last_prune_ms_ >= self.bucket_ms:
                self.prune(clock)
        return touched

    def add_station(self, reports: Iterable[dict], now_ms: int | None = None) -> set[str]:
        """Fold roadside stations' friction evidence into the map: dicts with station_id, cell (H3 at the map's
        resolution), timestamp_ms, mu, mu_lower, mu_upper (a 90 % interval). A station's newest report in a cell
        replaces its earlier ones there. The cells touched."""
        touched: set[str] = set()
        for report in reports:
            station, cell_id, t = str(report["station_id"]), report["cell"], int(report["timestamp_ms"])
            if h3.get_resolution(cell_id) != self.resolution:
                raise ValueError(
                    f"station {station!r}: cell {cell_id!r} is not at the map's resolution {self.resolution}"
                )
            checks.interval(
                f"report of station {station!r} at {t}", report["mu_lower"], report["mu_upper"], report["mu"]
            )
            cell = self.cells_by_id_.get(cell_id)
            if cell is None:
                cell = self.cells_by_id_[cell_id] = _Cell(cell_id)
            previous = cell.stations.get(station)
            if previous is not None and previous[0] > t:
                continue
            ll = self.interval_log_likelihood([report["mu_lower"]], [report["mu_upper"]])[0]
            cell.stations[station] = (t, ll)
            cell.last_ms = max(cell.last_ms, t)
            self.newest_ms_ = t if self.newest_ms_ is None else max(self.newest_ms_, t)
            touched.add(cell_id)
        if now_ms is not None and now_ms - self.last_prune_ms_ >= self.bucket_ms:
            self.prune(now_ms)
        return touched

    def _fold(self, p: _Pass) -> None:
        """A finished pass into its cell's bucket (its time: its last estimate)."""
        cell = self.cells_by_id_.get(p.cell)
        if cell is None:  # pruned while the pass was open
            cell = self.cells_by_id_[p.cell] = _Cell(p.cell)
            cell.last_ms = p.last_ms
        t = p.last_ms
        key = t // self.bucket_ms
        b = cell.buckets.get(key)
        if b is None:
            b = cell.buckets[key] = [t, 0.0, None, 0, 0, 0, 0, t, None, 0.0]
        ll = self._pass_log_likelihood(p)
        if ll is not None:
            half_life_ms = self.half_life_s * 1000.0
            if t > b[_REF] or b[_LL] is None:
                scale = 2.0 ** ((b[_REF] - t) / half_life_ms)  # re-anchor at the newest: sums *= 2^-(t - ref)/h
                b[_W] *= scale
                if b[_LL] is not None:
                    b[_LL] *= scale
                b[_REF] = t
                f = 1.0
            else:
                f = 2.0 ** ((t - b[_REF]) / half_life_ms)
            b[_W] += f
            b[_LL] = f * ll if b[_LL] is None else b[_LL] + f * ll
        b[_NPASS] += 1
        b[_N] += p.n
        b[_NEXC] += p.n_exc
        b[_LAST] = max(b[_LAST], t)
        if p.n_exc:
            b[_NPASS_EXC] += 1
            b[_LASTEXC] = p.last_exc_ms if b[_LASTEXC] is None else max(b[_LASTEXC], p.last_exc_ms)
        if p.proven >= self.min_proven_mu:
            b[_PROVEN] = max(b[_PROVEN], p.proven)

    # -------------------------------------------------------------------------------------------------- pruning

    def prune(self, now_ms: int) -> int:
        """Fold the passes whose vehicle has been gone pass_gap_s, free the buckets, vehicles, station reports and
        cells whose newest evidence is older than max_age_s, forget the last pass of vehicles gone for as long; the
        cells removed."""
        self.passes_.close_idle(now_ms)
        max_age_ms = self.max_age_s * 1000.0
        self.passes_.forget(now_ms - max_age_ms)
        open_cells = {p.cell for p in self.open_passes_.values()}
        removed = []
        for cell_id, cell in self.cells_by_id_.items():
            for key in [k for k, b in cell.buckets.items() if now_ms - b[_LAST] > max_age_ms]:
                del cell.buckets[key]
            for vehicle in [v for v, t in cell.vehicles.items() if now_ms - t > max_age_ms]:
                del cell.vehicles[vehicle]
            for station in [s for s, (t, _) in cell.stations.items() if now_ms - t > max_age_ms]:
                del cell.stations[station]
            if not cell.buckets and not cell.stations and cell_id not in open_cells:
                removed.append(cell_id)
        for cell_id in removed:
            del self.cells_by_id_[cell_id]
        self.last_prune_ms_ = now_ms
        return len(removed)

    # ---------------------------------------------------------------------------------------------------- query

    def cells(self, now_ms: int) -> list[CellSummary]:
        """Every cell with evidence at most max_age_s old at now_ms, ordered by cell id."""
        half_life_ms = self.half_life_s * 1000.0
        max_age_ms = self.max_age_s * 1000.0
        open_by_cell: dict[str, list[_Pass]] = {}
        for p in self.open_passes_.values():
            if now_ms - p.last_ms <= max_age_ms:
                open_by_cell.setdefault(p.cell, []).append(p)
        rows = []
        logps = []
        for cell_id in sorted(self.cells_by_id_):
            cell = self.cells_by_id_[cell_id]
            if now_ms - cell.last_ms > max_age_ms:
                continue
            t_now = max(cell.last_ms, now_ms)  # ages never negative
            w = 0.0
            ll = None
            n = n_excited = n_passes = 0
            informative_excited = False
            last_excited = None
            proven = 0.0
            for b in cell.buckets.values():
                if now_ms - b[_LAST] > max_age_ms:
                    continue  # the whole bucket is older than max_age_s
                n += b[_N]
                n_excited += b[_NEXC]
                n_passes += b[_NPASS]
                informative_excited |= b[_NPASS_EXC] > 0
                proven = max(proven, b[_PROVEN])
                if b[_LASTEXC] is not None and (last_excited is None or b[_LASTEXC] > last_excited):
                    last_excited = b[_LASTEXC]
                if b[_LL] is not None:
                    fade = 2.0 ** ((b[_REF] - t_now) / half_life_ms)  # lazy decay from the anchor to now
                    w += b[_W] * fade
                    ll = b[_LL] * fade if ll is None else ll + b[_LL] * fade
            for p in open_by_cell.get(cell_id, ()):
                n += p.n
                n_excited += p.n_exc
                n_passes += 1
                pass_ll = self._pass_log_likelihood(p)
                if p.n_exc:
                    informative_excited = True
                    last_excited = p.last_exc_ms if last_excited is None else max(last_excited, p.last_exc_ms)
                if p.proven >= self.min_proven_mu:
                    proven = max(proven, p.proven)
                if pass_ll is not None:
                    fade = 2.0 ** ((p.last_ms - t_now) / half_life_ms)
                    w += fade
                    ll = pass_ll * fade if ll is None else ll + pass_ll * fade
            n_stations = 0
            for t, station_ll in cell.stations.values():
                if now_ms - t > max_age_ms:
                    continue
                n_stations += 1
                fade = 2.0 ** ((t - t_now) / half_life_ms)
                w += fade
                ll = station_ll * fade if ll is None else ll + station_ll * fade
                last_excited = t if last_excited is None else max(last_excited, t)
            n_vehicles = sum(1 for t in cell.vehicles.values() if now_ms - t <= max_age_ms)
            if ll is not None and (informative_excited or n_stations):
                status = MEASURED
            elif ll is not None:
                status = BOUNDED
            else:
                status = NO_RECENT_EXCITED
            rows.append(
                (cell_id, cell, w, n, n_excited, n_vehicles, last_excited, status, n_passes, n_stations, proven)
            )
            if ll is not None:
                logps.append(ll * min(1.0, self.max_independent / w))
        quantiles = iter(posterior_quantiles(np.array(logps)) if logps else ())
        out = []
        for cell_id, cell, w, n, n_excited, n_vehicles, last_excited, status, n_passes, n_stations, proven in rows:
            lower = mu = upper = None
            if status != NO_RECENT_EXCITED:
                lower, mu, upper = (float(q) for q in next(quantiles))
            out.append(
                CellSummary(
                    cell=cell_id,
                    latitude_deg=cell.latitude_deg,
                    longitude_deg=cell.longitude_deg,
                    mu=mu,
                    mu_lower=lower,
                    mu_upper=upper,
                    weight=w,
                    n_estimates=n,
                    n_excited=n_excited,
                    n_vehicles=n_vehicles,
                    last_ms=cell.last_ms,
                    last_excited_ms=last_excited,
                    status=status,
                    n_passes=n_passes,
                    n_stations=n_stations,
                    mu_proven=proven if proven > 0.0 else None,
                )
            )
        return out

    # -------------------------------------------------------------------------------------------- cell states

    def cell_states(self, cell_ids: Iterable[str]) -> dict[str, dict]:
        """The state of each of `cell_ids` the map holds, as JSON-able dicts (`load_cell_states` takes them back):
        its time buckets, the passes in progress in it, its station reports and vehicles. What `cells(now)` says of
        the cell at any later `now` follows from it alone, so a reader that loads the states of a region gets the same
        summaries, faded the same (cluster mode, roadgrip/cloud/cluster/regions.py). Log-likelihoods travel as base64
        of little-endian float64: exact."""
        open_by_cell: dict[str, list[_Pass]] = {}
        for p in self.open_passes_.values():
            open_by_cell.setdefault(p.cell, []).append(p)
        states = {}
        for cell_id in cell_ids:
            cell = self.cells_by_id_.get(cell_id)
            if cell is None:
                continue
            states[cell_id] = {
                "last_ms": cell.last_ms,
                "buckets": [[key, *b[:_LL], _pack(b[_LL]), *b[_LL + 1 :]] for key, b in sorted(cell.buckets.items())],
                "open": [
                    [p.vehicle_id, p.first_ms, p.last_ms, _pack(p.ll), p.n, p.n_exc, p.last_exc_ms, p.proven]
                    for p in sorted(open_by_cell.get(cell_id, ()), key=operator.attrgetter("vehicle_id"))
                ],
                "stations": [[station, t, _pack(ll)] for station, (t, ll) in sorted(cell.stations.items())],
                "vehicles": dict(sorted(cell.vehicles.items())),
            }
        return states

    def load_cell_states(self, states: dict[str, dict]) -> None:
        """Take cells back from `cell_states` (replacing cells of the same id). A vehicle's pass in progress stays in
        progress unless the map holds a newer one of it (a state saved before the vehicle moved on): that older one
        is folded into its cell, as the map that saved it did when the vehicle moved on."""
        for cell_id, state in states.items():
            cell = self.cells_by_id_[cell_id] = _Cell(cell_id)
            cell.last_ms = int(state["last_ms"])
            cell.buckets = {int(key): [ref, w, _unpack(ll), *rest] for key, ref, w, ll, *rest in state["buckets"]}
            cell.stations = {station: (int(t), _unpack(ll)) for station, t, ll in state["stations"]}
            cell.vehicles = {vehicle: int(t) for vehicle, t in state["vehicles"].items()}
            for vehicle, first_ms, last_ms, ll, n, n_exc, last_exc_ms, proven in state["open"]:
                p = _Pass(vehicle, cell_id, int(first_ms))
                p.last_ms, p.ll, p.n, p.n_exc = int(last_ms), _unpack(ll), n, n_exc
                p.last_exc_ms, p.proven = last_exc_ms, float(proven)
                self.passes_.resume(p)
            if self.newest_ms_ is None or cell.last_ms > self.newest_ms_:
                self.newest_ms_ = cell.last_ms

    def clear(self) -> None:
        self.cells_by_id_.clear()
        self.passes_.clear()
        self.newest_ms_ = None
        self.last_prune_ms_ = _NEVER
