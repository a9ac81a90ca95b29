"""The friction map against closed forms (weighted means, the half-life), a brute-force second implementation, and its
invariants (age limits, positions, GeoJSON geometry)."""

import calendar
import math

import h3
import numpy as np
import pytest

from roadgrip.cloud.friction_map import Z90, CellSummary, FrictionMap

T0_MS = calendar.timegm((2026, 1, 15, 8, 0, 0)) * 1000
HEBEI = (38.0, 114.5)  # latitude, longitude in degrees


def est(t_ms=T0_MS, mu=0.5, lo=0.4, hi=0.6, excited=True, vehicle="v1", lat=HEBEI[0], lon=HEBEI[1]):
    return {"vehicle_id": vehicle, "timestamp_ms": t_ms, "latitude_deg": lat, "longitude_deg": lon,
            "mu": mu, "mu_lower": lo, "mu_upper": hi, "excited": excited}


def only_cell(fmap: FrictionMap, now_ms: int) -> CellSummary:
    cells = fmap.cells(now_ms)
    assert len(cells) == 1
    return cells[0]


def closed_form(rows, now_ms, half_life_s=600.0, floor=0.2):
    """The module docstring's formulas over a list of excited rows, written out directly."""
    w = np.array([2.0 ** (-max(0, now_ms - r["timestamp_ms"]) / (half_life_s * 1000.0))
                  / max(r["mu_upper"] - r["mu_lower"], floor) ** 2 for r in rows])
    mu_i = np.array([r["mu"] for r in rows])
    lo_i = np.array([r["mu_lower"] for r in rows])
    hi_i = np.array([r["mu_upper"] for r in rows])
    mu = np.sum(w * mu_i) / np.sum(w)
    spread = Z90 * math.sqrt(max(0.0, np.sum(w * (mu_i - mu) ** 2) / np.sum(w)))
    lower = max(0.0, mu - math.hypot(mu - np.sum(w * lo_i) / np.sum(w), spread))
    upper = mu + math.hypot(np.sum(w * hi_i) / np.sum(w) - mu, spread)
    return mu, lower, upper, np.sum(w)


def test_a_single_estimate_is_the_cell():
    fmap = FrictionMap()
    touched = fmap.add([est(mu=0.31, lo=0.2, hi=0.5)])
    cell = only_cell(fmap, T0_MS)
    assert touched == {cell.cell} == {h3.latlng_to_cell(*HEBEI, 10)}
    assert (cell.mu, cell.mu_lower, cell.mu_upper) == pytest.approx((0.31, 0.2, 0.5))
    assert cell.weight == pytest.approx(1.0 / 0.3**2)
    assert (cell.n_estimates, cell.n_excited, cell.n_vehicles) == (1, 1, 1)
    assert cell.status == "measured" and cell.last_ms == cell.last_excited_ms == T0_MS
    assert h3.latlng_to_cell(cell.latitude_deg, cell.longitude_deg, 10) == cell.cell


def test_two_estimates_give_the_inverse_squared_width_weighted_mean():
    fmap = FrictionMap()
    fmap.add([est(mu=0.3, lo=0.2, hi=0.5), est(mu=0.6, lo=0.5, hi=0.9, vehicle="v2")])
    cell = only_cell(fmap, T0_MS)
    w1, w2 = 1 / 0.3**2, 1 / 0.4**2
    mu = (w1 * 0.3 + w2 * 0.6) / (w1 + w2)
    lo_bar, hi_bar = (w1 * 0.2 + w2 * 0.5) / (w1 + w2), (w1 * 0.5 + w2 * 0.9) / (w1 + w2)
    s_b = math.sqrt((w1 * (0.3 - mu) ** 2 + w2 * (0.6 - mu) ** 2) / (w1 + w2))
    assert cell.mu == pytest.approx(mu)
    assert cell.mu_lower == pytest.approx(mu - math.hypot(mu - lo_bar, 1.6448536 * s_b))
    assert cell.mu_upper == pytest.approx(mu + math.hypot(hi_bar - mu, 1.6448536 * s_b))
    assert cell.weight == pytest.approx(w1 + w2)
    assert cell.n_vehicles == 2


def test_agreeing_estimates_give_the_weighted_mean_of_their_bounds():
    fmap = FrictionMap()
    fmap.add([est(mu=0.5, lo=0.4, hi=0.7), est(mu=0.5, lo=0.3, hi=0.8, t_ms=T0_MS + 100)])
    cell = only_cell(fmap, T0_MS + 100)
    w1, w2 = 1 / 0.3**2 * 2 ** (-0.1 / 600), 1 / 0.5**2
    assert cell.mu == pytest.approx(0.5)
    assert cell.mu_lower == pytest.approx((w1 * 0.4 + w2 * 0.3) / (w1 + w2), abs=1e-6)
    assert cell.mu_upper == pytest.approx((w1 * 0.7 + w2 * 0.8) / (w1 + w2), abs=1e-6)


def test_disagreeing_estimates_widen_the_interval_to_cover_both():
    fmap = FrictionMap()
    fmap.add([est(mu=0.2, lo=0.1, hi=0.3), est(mu=0.8, lo=0.7, hi=0.9, vehicle="v2")])
    cell = only_cell(fmap, T0_MS)
    assert cell.mu == pytest.approx(0.5)
    assert cell.mu_lower < 0.2 and cell.mu_upper > 0.8  # the mean of the bounds, [0.4, 0.6], would cover neither


def test_an_estimate_one_half_life_old_weighs_exactly_half():
    half_life_ms = 600_000
    old = est(t_ms=T0_MS, mu=0.2, lo=0.1, hi=0.4)
    new = est(t_ms=T0_MS + half_life_ms, mu=0.8, lo=0.7, hi=1.0)
    for order in ([old, new], [new, old]):  # out of order too: the re-anchoring is exact
        fmap = FrictionMap(half_life_s=600.0)
        fmap.add(order)
        cell = only_cell(fmap, T0_MS + half_life_ms)
        assert cell.mu == pytest.approx((0.5 * 0.2 + 1.0 * 0.8) / 1.5)
        assert cell.weight == pytest.approx(1.5 / 0.3**2)
    fmap = FrictionMap(half_life_s=600.0)
    fmap.add([old])
    assert only_cell(fmap, T0_MS + half_life_ms).weight == pytest.approx(0.5 / 0.3**2)
    assert only_cell(fmap, T0_MS + 2 * half_life_ms).weight == pytest.approx(0.25 / 0.3**2)


def test_the_width_floor_caps_an_over_confident_estimate():
    fmap = FrictionMap(min_interval_width=0.2)
    fmap.add([est(mu=0.9, lo=0.899, hi=0.901), est(mu=0.3, lo=0.2, hi=0.4, vehicle="v2")])
    cell = only_cell(fmap, T0_MS)
    assert cell.mu == pytest.approx(0.6)  # both weigh 1 / 0.2^2
    assert cell.weight == pytest.approx(2 / 0.2**2)


def test_ages_are_never_negative():
    fmap = FrictionMap()
    fmap.add([est(t_ms=T0_MS + 5000)])
    assert only_cell(fmap, T0_MS).weight == pytest.approx(1 / 0.2**2)  # a terminal ahead of the server: no boost


def test_non_excited_estimates_count_but_say_nothing_about_mu():
    fmap = FrictionMap()
    fmap.add([est(mu=0.5, lo=0.0, hi=1.2, excited=False), est(mu=0.5, lo=0.0, hi=1.2, excited=False, vehicle="v2")])
    cell = only_cell(fmap, T0_MS)
    assert cell.status == "no_recent_excited_evidence"
    assert cell.mu is None and cell.mu_lower is None and cell.mu_upper is None
    assert (cell.weight, cell.n_estimates, cell.n_excited, cell.n_vehicles) == (0.0, 2, 0, 2)
    assert cell.last_excited_ms is None
    fmap.add([est(mu=0.3, lo=0.2, hi=0.4, t_ms=T0_MS + 10)])
    cell = only_cell(fmap, T0_MS + 10)
    assert cell.mu == pytest.approx(0.3) and cell.n_estimates == 3  # non-excited rows did not pull it


def test_excited_evidence_older_than_max_age_is_not_recent():
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
    assert fmap.cells_by_id_ == {}
    fmap.add([est(t_ms=T0_MS)])
    fmap.add([est(t_ms=T0_MS + 7_200_000, lat=39.0)])  # the data clock moves on: add() prunes by itself
    assert len(fmap.cells_by_id_) == 1


def test_evidence_beyond_max_age_no_longer_counts_in_a_living_cell():
    fmap = FrictionMap(max_age_s=3600.0)
    late_ms = T0_MS + 3_600_000 + fmap.bucket_ms + 1
    fmap.add([est(t_ms=T0_MS, mu=0.2, lo=0.1, hi=0.3), est(t_ms=late_ms, mu=0.8, lo=0.7, hi=0.9)])
    cell = only_cell(fmap, late_ms)
    assert cell.mu == pytest.approx(0.8) and cell.n_estimates == 1  # faded is not enough: it is gone


def test_agrees_with_a_brute_force_implementation():
    rng = np.random.default_rng(7)
    rows = []
    for k in range(400):
        mu = float(rng.uniform(0.1, 1.0))
        half = float(rng.uniform(0.01, 0.4))
        rows.append(est(t_ms=T0_MS + int(rng.integers(0, 3_000_000)), mu=mu, lo=mu - half * rng.uniform(0.5, 1.5),
                        hi=mu + half, excited=bool(rng.random() < 0.7), vehicle=f"v{k % 9}",
                        lat=38.0 + float(rng.uniform(0, 0.004)), lon=114.5 + float(rng.uniform(0, 0.004))))
    fmap = FrictionMap()
    for start in range(0, len(rows), 37):  # in batches, out of time order
        fmap.add(rows[start:start + 37])
    now_ms = T0_MS + 3_100_000
    cells = fmap.cells(now_ms)
    assert {c.cell for c in cells} == {fmap.cell_of(r["latitude_deg"], r["longitude_deg"]) for r in rows}
    for cell in cells:
        mine = [r for r in rows if fmap.cell_of(r["latitude_deg"], r["longitude_deg"]) == cell.cell]
        excited = [r for r in mine if r["excited"]]
        assert cell.n_estimates == len(mine) and cell.n_excited == len(excited)
        assert cell.n_vehicles == len({r["vehicle_id"] for r in mine})
        assert cell.last_ms == max(r["timestamp_ms"] for r in mine)
        if not excited:
            assert cell.mu is None
            continue
        mu, lower, upper, weight = closed_form(excited, now_ms)
        assert (cell.mu, cell.mu_lower, cell.mu_upper) == pytest.approx((mu, lower, upper), abs=1e-9)
        assert cell.weight == pytest.approx(weight, rel=1e-9)
        assert cell.mu_lower <= cell.mu <= cell.mu_upper


def test_bad_excited_estimates_are_refused_with_their_values():
    with pytest.raises(ValueError, match=r"mu_lower 0\.7.*mu_upper 0\.2"):
        FrictionMap().add([est(mu=0.5, lo=0.7, hi=0.2)])
    with pytest.raises(ValueError, match="nan"):
        FrictionMap().add([est(mu=float("nan"))])


def test_geojson_polygons_are_closed_rings_in_lon_lat_order():
    fmap = FrictionMap()
    fmap.add([est(), est(lat=38.01, lon=114.51, excited=False)])
    collection = fmap.to_geojson(T0_MS)
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


@pytest.mark.parametrize("name", ["half_life_s", "max_age_s", "min_interval_width"])
@pytest.mark.parametrize("value", [0, -1.0, float("inf"), float("nan")])
def test_times_and_floor_are_validated(name, value):
    with pytest.raises(ValueError, match=name):
        FrictionMap(**{name: value})


def test_other_resolutions_and_clear():
    fmap = FrictionMap(resolution=9)
    fmap.add([est()])
    assert only_cell(fmap, T0_MS).cell == h3.latlng_to_cell(*HEBEI, 9)
    fmap.clear()
    assert fmap.cells(T0_MS) == []
