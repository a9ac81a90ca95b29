"""The friction map against closed forms (a plateau's quantiles, the half-life), a brute-force second implementation of
its posterior, what it must conclude (passes count once, calm passes prove their bound, robustness to one wrong
estimate, a dried patch), and its invariants (age limits, positions, stations, GeoJSON geometry)."""

import calendar

import h3
import numpy as np
import pytest
from scipy.stats import norm

from roadgrip.cloud.domain.friction_map import MU_GRID, CellSummary, FrictionMap, posterior_quantiles
from roadgrip.cloud.formats.geojson import geojson

T0_MS = calendar.timegm((2026, 1, 15, 8, 0, 0)) * 1000
HEBEI = (38.0, 114.5)  # latitude, longitude in degrees
MIN_MS = 60_000


def est(t_ms=T0_MS, mu=0.5, lo=0.4, hi=0.6, excited=True, vehicle="v1", lat=HEBEI[0], lon=HEBEI[1], proven=None):
    return {
        "vehicle_id": vehicle,
        "timestamp_ms": t_ms,
        "latitude_deg": lat,
        "longitude_deg": lon,
        "mu": mu,
        "mu_lower": lo,
        "mu_upper": hi,
        "excited": excited,
        "mu_proven": proven,
    }


def only_cell(fmap: FrictionMap, now_ms: int) -> CellSummary:
    cells = fmap.cells(now_ms)
    assert len(cells) == 1
    return cells[0]


def test_quantiles_of_a_flat_posterior_are_its_closed_form():
    logp = np.where((MU_GRID >= 0.2 - 1e-9) & (MU_GRID <= 0.6 + 1e-9), 0.0, -80.0)
    lower, median, upper = posterior_quantiles(logp)[0]
    # trapezoids: the density ramps over one grid step at each end, so the support is 0.18..0.62 less half a step
    assert median == pytest.approx(0.4, abs=1e-9)
    assert lower == pytest.approx(0.2 + 0.05 * 0.4, abs=0.011) and upper == pytest.approx(0.6 - 0.05 * 0.4, abs=0.011)


def single(lo, hi, **options) -> CellSummary:
    fmap = FrictionMap(**options)
    fmap.add([est(mu=(lo + hi) / 2, lo=lo, hi=hi)])
    return only_cell(fmap, T0_MS)


def test_a_single_estimate_bounds_the_cell_from_above_and_proves_grip_only_where_it_drove():
    fmap = FrictionMap()
    touched = fmap.add([est(mu=0.31, lo=0.2, hi=0.6)])
    cell = only_cell(fmap, T0_MS)
    assert touched == {cell.cell} == {h3.latlng_to_cell(*HEBEI, 10)}
    assert cell.mu_upper == pytest.approx(0.6, abs=0.03)  # a low reading proves a slippery spot in the cell
    assert cell.mu_lower < 0.1  # grip at the spot it braked on: the rest of the cell may hold a patch
    # without that locality the plateau gives back the estimate's own 90 % interval, and its middle
    local = single(0.2, 0.6, grip_locality=0.005)
    assert local.mu_lower == pytest.approx(0.2, abs=0.03) and local.mu_upper == pytest.approx(0.6, abs=0.03)
    assert local.mu == pytest.approx(0.4, abs=0.01)
    assert cell.weight == pytest.approx(1.0)
    assert (cell.n_estimates, cell.n_excited, cell.n_vehicles, cell.n_passes) == (1, 1, 1, 1)
    assert cell.status == "measured" and cell.last_ms == cell.last_excited_ms == T0_MS
    assert h3.latlng_to_cell(cell.latitude_deg, cell.longitude_deg, 10) == cell.cell


def test_one_pass_counts_once_however_many_samples_it_has():
    one, many = FrictionMap(), FrictionMap()
    one.add([est(t_ms=T0_MS + 4900, lo=0.1, hi=0.3)])
    many.add([est(t_ms=T0_MS + 100 * k, lo=0.1, hi=0.3) for k in range(50)])
    a, b = only_cell(one, T0_MS + 4900), only_cell(many, T0_MS + 4900)
    assert (b.mu_lower, b.mu, b.mu_upper) == pytest.approx((a.mu_lower, a.mu, a.mu_upper), abs=1e-9)
    assert (b.n_estimates, b.n_passes) == (50, 1)


def test_independent_passes_that_agree_narrow_the_interval():
    fmap = FrictionMap()
    fmap.add([est(lo=0.1, hi=0.3)])
    single = only_cell(fmap, T0_MS)
    fmap.add([est(lo=0.1, hi=0.3, vehicle=f"v{k}") for k in range(2, 6)])
    fused = only_cell(fmap, T0_MS)
    assert fused.mu_upper - fused.mu_lower < single.mu_upper - single.mu_lower
    assert 0.05 < fused.mu_lower < fused.mu < fused.mu_upper < 0.32
    assert fused.n_vehicles == 5 and fused.weight == pytest.approx(5.0)


def test_calm_passes_prove_their_bound():
    fmap = FrictionMap()
    fmap.add([est(mu=0.8, lo=0.1, hi=1.2, excited=False, proven=0.4)])
    one = only_cell(fmap, T0_MS)
    assert one.status == "bounded" and one.mu_proven == pytest.approx(0.4)
    assert 0.0 < one.mu_lower < 0.4 < one.mu and one.mu_upper > 1.4  # one pass: grip where it cornered
    assert one.n_excited == 0 and one.last_excited_ms is None
    fmap.add([est(mu=0.8, lo=0.1, hi=1.2, excited=False, proven=0.4, vehicle=f"v{k}") for k in range(2, 5)])
    four = only_cell(fmap, T0_MS)
    # four passes: below the bound the likelihood is 0.5^4 (capped at 3 independent passes: 0.5^3) of above it
    assert 0.35 < four.mu_lower < 0.5 and four.mu_upper > 1.4


def test_an_interval_open_above_leaves_dry_asphalt_inside():
    fmap = FrictionMap()
    fmap.add([est(mu=0.9, lo=0.6, hi=1.2, vehicle=f"v{k}") for k in range(4)])  # "mu >= 0.6": nothing more
    cell = only_cell(fmap, T0_MS)
    assert cell.mu_lower < 0.6 < cell.mu and cell.mu_lower < 1.17 < cell.mu_upper


def test_a_bound_below_min_proven_is_no_evidence():
    fmap = FrictionMap(min_proven_mu=0.1)
    fmap.add([est(excited=False, proven=0.05), est(excited=False, vehicle="v2")])
    cell = only_cell(fmap, T0_MS)
    assert cell.status == "no_recent_excited_evidence" and cell.mu is None and cell.mu_proven is None
    assert (cell.weight, cell.n_estimates, cell.n_excited, cell.n_vehicles) == (0.0, 2, 0, 2)


def test_non_excited_intervals_do_not_pull_the_cell():
    fmap = FrictionMap()
    fmap.add([est(mu=0.9, lo=0.5, hi=1.2, excited=False, vehicle=f"v{k}") for k in range(5)])
    fmap.add([est(mu=0.2, lo=0.1, hi=0.3, vehicle="ice")])
    cell = only_cell(fmap, T0_MS)
    assert cell.mu == pytest.approx(single(0.1, 0.3).mu, abs=1e-12) and cell.n_estimates == 6


def test_one_confident_wrong_estimate_does_not_veto_the_others():
    fmap = FrictionMap()
    fmap.add([est(lo=0.6, hi=1.0, vehicle=f"v{k}") for k in range(5)] + [est(lo=0.1, hi=0.12, vehicle="wrong")])
    cell = only_cell(fmap, T0_MS)
    assert 0.6 < cell.mu < 1.0 and cell.mu_upper > 0.9


def test_a_dried_patch_holds_until_its_evidence_fades_under_recent_grip():
    fmap = FrictionMap(half_life_s=600.0)
    fmap.add([est(t_ms=T0_MS, lo=0.05, hi=0.25, vehicle=f"ice{k}") for k in range(3)])
    soon_ms = T0_MS + 5 * MIN_MS
    fmap.add(
        [est(t_ms=soon_ms, mu=0.9, lo=0.2, hi=1.2, excited=False, proven=0.55, vehicle=f"dry{k}") for k in range(4)]
    )
    assert only_cell(fmap, soon_ms).mu < 0.25  # slippery readings of 5 minutes ago still hold the cell
    late_ms = T0_MS + 30 * MIN_MS
    fmap.add(
        [est(t_ms=late_ms, mu=0.9, lo=0.2, hi=1.2, excited=False, proven=0.55, vehicle=f"late{k}") for k in range(4)]
    )
    cell = only_cell(fmap, late_ms)
    assert cell.mu > 0.55 and cell.mu_upper > 1.17  # three half-lives on, passes proving grip outweigh them


def test_a_pass_one_half_life_old_weighs_half():
    fmap = FrictionMap(half_life_s=600.0)
    fmap.add([est(t_ms=T0_MS)])
    assert only_cell(fmap, T0_MS + 600_000).weight == pytest.approx(0.5)
    fmap.prune(T0_MS + 600_000)  # the pass is folded into its bucket: the same weight
    assert not fmap.open_passes_
    assert only_cell(fmap, T0_MS + 600_000).weight == pytest.approx(0.5)
    assert only_cell(fmap, T0_MS + 1_200_000).weight == pytest.approx(0.25)


def test_ages_are_never_negative():
    fmap = FrictionMap()
    fmap.add([est(t_ms=T0_MS + 5000)])
    assert only_cell(fmap, T0_MS).weight == pytest.approx(1.0)  # a terminal ahead of the server: no boost


def brute_force(rows, now_ms, fmap: FrictionMap):
    """The module docstring's posterior over the given rows, written out directly: passes per vehicle and cell in time
    order, the mean of their excited rows' two soft steps plus the soft step of their largest bound, aged."""

    def soft(z, eps=fmap.outlier_rate):
        return np.log(eps + (1 - eps) * norm.cdf(z))

    by_cell = {}
    for vehicle in sorted({r["vehicle_id"] for r in rows}):
        mine = sorted((r for r in rows if r["vehicle_id"] == vehicle), key=lambda r: r["timestamp_ms"])
        passes, current = [], None
        for r in mine:
            cell = fmap.cell_of(r["latitude_deg"], r["longitude_deg"])
            if current is None or current[0] != cell or r["timestamp_ms"] - current[1][-1]["timestamp_ms"] > 30_000:
                current = (cell, [])
                passes.append(current)
            current[1].append(r)
        for cell, members in passes:
            excited = [r for r in members if r["excited"]]
            ll = np.zeros_like(MU_GRID)
            informative = False
            for r in excited:
                s = max(r["mu_upper"] - r["mu_lower"], fmap.min_interval_width) / 8
                step = soft((MU_GRID - r["mu_lower"]) / s, fmap.grip_locality)
                if r["mu_upper"] < 1.2:  # the estimators' "nothing known above"
                    step = step + soft((r["mu_upper"] - MU_GRID) / s)
                ll += step / len(excited)
                informative = True
            proven = max((r["mu_proven"] or 0.0 for r in members), default=0.0)
            if proven >= fmap.min_proven_mu:
                ll += soft((MU_GRID - proven) / fmap.proven_sigma, fmap.grip_locality)
                informative = True
            age_s = (now_ms - members[-1]["timestamp_ms"]) / 1000.0
            entry = by_cell.setdefault(cell, [np.zeros_like(MU_GRID), 0.0, 0])
            entry[2] += 1
            if informative:
                entry[0] += 2.0 ** (-age_s / fmap.half_life_s) * ll
                entry[1] += 2.0 ** (-age_s / fmap.half_life_s)
    return by_cell


def test_agrees_with_a_brute_force_implementation():
    rng = np.random.default_rng(7)
    rows = []
    for k in range(9):
        t = T0_MS + int(rng.integers(0, 600_000))
        lat, lon = 38.0, 114.5
        for _ in range(60):  # a drive: 100 ms steps east along a line, some calm, some excited
            t += 100 + int(rng.integers(0, 3)) * 20_000  # now and then a stop long enough to end a pass
            lon += float(rng.uniform(0, 0.0004))
            mu = float(rng.uniform(0.1, 1.0))
            excited = bool(rng.random() < 0.5)
            proven = float(rng.uniform(0.0, mu))
            rows.append(
                est(
                    t_ms=t,
                    mu=mu,
                    lo=max(0.0, mu - rng.uniform(0.05, 0.4)),
                    hi=min(1.2, mu + rng.uniform(0.05, 0.4)),
                    excited=excited,
                    vehicle=f"v{k}",
                    lat=lat + float(rng.normal(0, 2e-5)),
                    lon=lon,
                    proven=proven,
                )
            )
    fmap = FrictionMap()
    order = sorted(rows, key=lambda r: r["timestamp_ms"])
    for start in range(0, len(order), 37):  # in time-ordered batches of many vehicles, as the service sends them
        fmap.add(order[start : start + 37])
    now_ms = max(r["timestamp_ms"] for r in rows) + 1000
    expected = brute_force(rows, now_ms, fmap)
    cells = fmap.cells(now_ms)
    assert {c.cell for c in cells} == set(expected)
    for cell in cells:
        ll, weight, n_passes = expected[cell.cell]
        mine = [r for r in rows if fmap.cell_of(r["latitude_deg"], r["longitude_deg"]) == cell.cell]
        assert cell.n_estimates == len(mine) and cell.n_excited == sum(r["excited"] for r in mine)
        assert cell.n_vehicles == len({r["vehicle_id"] for r in mine}) and cell.n_passes == n_passes
        assert cell.weight == pytest.approx(weight, rel=1e-9)
        if weight == 0.0:
            assert cell.mu is None
            continue
        capped = ll * min(1.0, fmap.max_independent / weight)
        assert (cell.mu_lower, cell.mu, cell.mu_upper) == pytest.approx(tuple(posterior_quantiles(capped)[0]), abs=1e-9)
        assert 0.0 <= cell.mu_lower <= cell.mu <= cell.mu_upper <= MU_GRID[-1]


def test_a_station_report_is_evidence_and_its_newest_replaces_the_older():
    fmap = FrictionMap()
    cell_id = fmap.cell_of(*HEBEI)
    report = {
        "station_id": "rws-1",
        "cell": cell_id,
        "timestamp_ms": T0_MS,
        "mu": 0.15,
        "mu_lower": 0.05,
        "mu_upper": 0.3,
    }
    assert fmap.add_station([report]) == {cell_id}
    cell = only_cell(fmap, T0_MS)
    assert cell.status == "measured" and cell.n_stations == 1 and cell.n_estimates == 0
    assert cell.mu_lower < cell.mu < cell.mu_upper < 0.33
    fmap.add_station(
        [
            {**report, "timestamp_ms": T0_MS + MIN_MS, "mu": 0.8, "mu_lower": 0.6, "mu_upper": 1.0},
            {**report, "timestamp_ms": T0_MS - MIN_MS},
        ]
    )  # an older report arriving late is ignored
    cell = only_cell(fmap, T0_MS + MIN_MS)
    assert cell.n_stations == 1 and cell.mu_lower < 0.6 < cell.mu < cell.mu_upper < 1.02
    with pytest.raises(ValueError, match="resolution 10"):
        fmap.add_station([{**report, "cell": h3.latlng_to_cell(*HEBEI, 9)}])
    with pytest.raises(ValueError, match="station 'rws-1'.*mu_lower 0.9"):
        fmap.add_station([{**report, "mu_lower": 0.9, "mu_upper": 0.2}])


def test_evidence_older_than_max_age_is_not_recent():
    fmap = FrictionMap(max_age_s=3600.0)
    fmap.add([est(t_ms=T0_MS), est(t_ms=T0_MS + 3_000_000, excited=False)])
    assert only_cell(fmap, T0_MS + 3_600_000).status == "measured"
    cell = only_cell(fmap, T0_MS + 3_600_001)
    assert cell.status == "no_recent_excited_evidence" and cell.mu is None


def test_rows_without_position_are_ignored():
    fmap = FrictionMap()
    assert fmap.add([est(lat=None), est(lon=None), est(lat=None, lon=None)]) == set()
    assert fmap.cells(T0_MS) == []


def test_cells_older_than_max_age_vanish_and_are_freed():
    fmap = FrictionMap(max_age_s=3600.0)
    fmap.add([est(t_ms=T0_MS)])
    assert len(fmap.cells(T0_MS + 3_600_000)) == 1
    assert fmap.cells(T0_MS + 3_600_001) == []
    assert fmap.prune(T0_MS + 3_600_001) == 1
    assert fmap.cells_by_id_ == {} and fmap.open_passes_ == {}
    fmap.add([est(t_ms=T0_MS)])
    fmap.add([est(t_ms=T0_MS + 7_200_000, lat=39.0)])  # the data clock moves on: add() prunes by itself
    assert len(fmap.cells_by_id_) == 1


def test_evidence_beyond_max_age_no_longer_counts_in_a_living_cell():
    fmap = FrictionMap(max_age_s=3600.0)
    late_ms = T0_MS + 3_600_000 + fmap.bucket_ms + 1
    fmap.add([est(t_ms=T0_MS, lo=0.1, hi=0.3, vehicle="old"), est(t_ms=late_ms, lo=0.7, hi=0.9)])
    cell = only_cell(fmap, late_ms)
    assert cell.mu == pytest.approx(single(0.7, 0.9).mu, abs=1e-12) and cell.n_estimates == 1  # gone, not faded


def test_bad_excited_estimates_are_refused_with_their_values():
    with pytest.raises(ValueError, match=r"mu_lower 0\.7.*mu_upper 0\.2"):
        FrictionMap().add([est(mu=0.5, lo=0.7, hi=0.2)])
    with pytest.raises(ValueError, match="nan"):
        FrictionMap().add([est(mu=float("nan"))])


def test_geojson_polygons_are_closed_rings_in_lon_lat_order():
    fmap = FrictionMap()
    fmap.add([est(), est(lat=38.01, lon=114.51, excited=False, vehicle="v2")])
    collection = geojson(fmap.cells(T0_MS))
    assert collection["type"] == "FeatureCollection" and len(collection["features"]) == 2
    for feature in collection["features"]:
        ring = feature["geometry"]["coordinates"][0]
        assert feature["geometry"]["type"] == "Polygon"
        assert ring[0] == ring[-1] and len(ring) == 7  # a hexagon, closed
        assert abs(ring[0][0]) > abs(ring[0][1])  # [lon, lat]: 114.5 E before 38.0 N
        assert h3.latlng_to_cell(ring[0][1], ring[0][0], 10) in h3.grid_disk(feature["id"], 1)
        assert set(feature["properties"]) == set(CellSummary.__dataclass_fields__)
        assert feature["properties"]["cell"] == feature["id"]


@pytest.mark.parametrize("resolution", [-1, 16, 10.5, "10", True, None])
def test_resolution_is_validated(resolution):
    with pytest.raises(ValueError, match=rf"resolution.*{resolution!r}"):
        FrictionMap(resolution=resolution)


@pytest.mark.parametrize(
    "name",
    [
        "half_life_s",
        "max_age_s",
        "min_interval_width",
        "proven_sigma",
        "min_proven_mu",
        "pass_gap_s",
        "outlier_rate",
        "max_independent",
        "grip_locality",
    ],
)
@pytest.mark.parametrize("value", [0, -1.0, float("inf"), float("nan")])
def test_parameters_are_validated(name, value):
    with pytest.raises(ValueError, match=name):
        FrictionMap(**{name: value})


def test_other_resolutions_and_clear():
    fmap = FrictionMap(resolution=9)
    fmap.add([est()])
    assert only_cell(fmap, T0_MS).cell == h3.latlng_to_cell(*HEBEI, 9)
    fmap.clear()
    assert fmap.cells(T0_MS) == [] and fmap.open_passes_ == {}
