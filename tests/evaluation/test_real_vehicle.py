import csv
import math

import numpy as np
import pyarrow.compute as pc
import pyarrow.parquet as pq
import pytest
from typer.testing import CliRunner

from roadgrip.evaluation import real_vehicle as rv
from roadgrip.sim.roads import MuProfile
from roadgrip.units import kmh_to_mps
from roadgrip.vehicle.tires.burckhardt import SURFACES, peak_mu

SHORT_M = 1500.0  # a short section: the whole benchmark in seconds


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("real-vehicle")
    return out, rv.run_real_vehicle_benchmark(out, seed=0, length_m=SHORT_M)


def _read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def test_the_reverse_road_is_the_forward_road_reversed():
    road = rv.expressway(2000.0, np.random.default_rng(1))
    rev = road.reversed()
    assert rev.direction == "reverse" and rev.length_m == pytest.approx(road.length_m)
    np.testing.assert_array_equal(rev.path.points_m, road.path.points_m[::-1])
    s = np.linspace(0.0, road.length_m, 37)
    for fwd_mu, rev_mu in ((road.mu_dry, rev.mu_dry), (road.mu_wet, rev.mu_wet)):
        np.testing.assert_allclose(rev_mu.at(s, left=True), fwd_mu.at(road.length_m - s, left=False), atol=1e-12)
        np.testing.assert_allclose(rev_mu.at(s, left=False), fwd_mu.at(road.length_m - s, left=True), atol=1e-12)
    back = rev.reversed()
    assert back.direction == "forward"
    np.testing.assert_array_equal(back.path.points_m, road.path.points_m)
    np.testing.assert_allclose(back.mu_dry.table(), road.mu_dry.table())
    assert rev.route_mean(rev.mu_dry) == pytest.approx(road.route_mean(road.mu_dry))


def test_reversing_a_step_profile_keeps_each_value_on_its_stretch():
    mu = MuProfile([0.0, 100.0, 300.0], [0.2, 0.5, 0.9], [0.3, 0.6, 1.0], "step")
    rev = rv.reverse_profile(mu, 400.0)
    s = np.array([50.0, 150.0, 250.0, 350.0])  # mid-stretch stations, away from the steps
    np.testing.assert_allclose(rev.at(s, left=True), mu.at(400.0 - s, left=False))
    np.testing.assert_allclose(rev.at(s, left=False), mu.at(400.0 - s, left=True))


def test_expressway_geometry_and_friction():
    road = rv.expressway()
    assert road.length_m == pytest.approx(rv.ROAD_LENGTH_M, rel=1e-9)
    p = road.path.points_m
    a, b, c = p[:-2], p[1:-1], p[2:]  # circumradius of each three consecutive points
    cross = np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    sides = np.hypot(*(b - a).T) * np.hypot(*(c - b).T) * np.hypot(*(c - a).T)
    radius = np.where(cross > 1e-9, sides / (2.0 * np.maximum(cross, 1e-300)), np.inf)
    assert radius.min() >= 999.0 and np.isfinite(radius).any()
    dry_peak, wet_peak = (peak_mu(*SURFACES[n]) for n in ("dry_asphalt", "wet_asphalt"))
    assert (np.abs(road.mu_dry.mu_left / dry_peak - 1.0) <= 0.06 + 1e-12).all()
    np.testing.assert_allclose(road.mu_wet.mu_left / road.mu_dry.mu_left, wet_peak / dry_peak)  # one pavement
    assert road.mu_dry.mu_left.std() > 0.01, "mu varies along the road"


def test_test_drive_profile_accelerates_and_brakes_hard_enough_to_excite():
    rng = np.random.default_rng(5)
    profile = rv.test_drive_profile(10_000.0, rng)
    v, t = profile.speeds_mps, profile.times_s
    assert profile.distance_m(t[-1]) >= 10_000.0
    assert v.max() <= kmh_to_mps(115.0) + 1e-9 and v[1:].min() >= kmh_to_mps(55.0) - 1e-9
    slope = np.diff(v) / np.diff(t)
    assert slope[0] > 0, "accelerating first, as the paper's vehicle"
    assert (slope <= -rv.FULL_BRAKE_MPS2 + 1e-9).any() and (slope < -5.4).sum() >= 10
    again = rv.test_drive_profile(10_000.0, np.random.default_rng(5))
    np.testing.assert_array_equal(again.speeds_mps, v)


@pytest.mark.slow
def test_benchmark_on_a_short_road_writes_table_7(short_run):
    out, result = short_run
    table = _read(out / "table7.csv")
    assert [r["test_group"] for r in table] == [*rv.GROUPS, "mean", "ratio_wet_dry"]
    assert float(table[0]["paper_vehicle_based_estimate_dry"]) == 0.628
    ratio = table[-1]
    assert float(ratio["paper_vehicle_based_estimate_dry"]) == pytest.approx(0.4238 / 0.6065, abs=1e-3)
    for key in ("ours_ekf_dry", "ours_learned_dry", "true_dry_mu"):
        assert 0.3 < float(ratio[key]) < 1.5
    metrics = _read(out / "metrics.csv")
    assert len(metrics) == 4 and {m["direction"] for m in metrics} == {"forward", "reverse"}
    for m in metrics:
        assert float(m["sfc_wet"]) < float(m["true_wet_mu_route"]) + 0.05
        assert int(m["ekf_judged_excited"]) > 0
    ratios = {(r["source"], r["definition"][:4]): float(r["ratio"]) for r in _read(out / "ratios.csv")}
    assert ratios[("paper Table 7", "mean")] == pytest.approx(0.699, abs=1e-3)
    assert ratios[("Burckhardt model", "peak")] == pytest.approx(0.685, abs=1e-3)
    assert "Ratio wet/dry" in (out / "table7.md").read_text()
    assert result["figures"][0].stat().st_size > 20_000


@pytest.mark.slow
def test_group_value_is_the_mean_of_the_excited_estimates_on_the_section(short_run):
    out, result = short_run
    estimates = pq.read_table(out / "estimates.parquet")
    for row in result["metrics"]:
        for name in ("ekf", "learned"):
            own = estimates.filter(
                pc.and_(pc.equal(estimates["test_group"], row["test_group"]), pc.equal(estimates["estimator"], name))
            )
            mu, exc = own["mu"].to_numpy(), own["excited"].to_numpy()
            assert row[f"{name}_dry_excited_mean"] == pytest.approx(mu[exc].mean())
            assert row[f"{name}_dry_all_mean"] == pytest.approx(mu.mean())
            assert own["station_m"].to_numpy().max() <= SHORT_M + 1e-6


@pytest.mark.slow
def test_same_seed_same_table_other_seed_other_table(short_run, tmp_path):
    out, _ = short_run
    rv.run_real_vehicle_benchmark(tmp_path / "again", seed=0, length_m=SHORT_M)
    assert (tmp_path / "again" / "table7.csv").read_bytes() == (out / "table7.csv").read_bytes()
    assert (tmp_path / "again" / "metrics.csv").read_bytes() == (out / "metrics.csv").read_bytes()
    rv.run_real_vehicle_benchmark(tmp_path / "other", seed=1, length_m=SHORT_M, estimators=("ekf",))
    assert (tmp_path / "other" / "table7.csv").read_bytes() != (out / "table7.csv").read_bytes()


@pytest.mark.slow
def test_cli_runs_the_real_vehicle_benchmark(tmp_path, monkeypatch):
    from roadgrip.cli import app

    monkeypatch.setattr(rv, "ROAD_LENGTH_M", 800.0)
    result = CliRunner().invoke(app, ["evaluate", "--benchmark", "real-vehicle", "--out", str(tmp_path)])
    assert result.exit_code == 0, result.output
    assert len(_read(tmp_path / "table7.csv")) == 6 and (tmp_path / "table7.md").exists()


def test_burckhardt_ratio_definitions():
    peak, locked, at_slip, sfc_over_dry = rv.burckhardt_ratios()
    assert peak["ratio"] == pytest.approx(0.801 / 1.170, abs=1e-3)
    c = SURFACES["wet_asphalt"]
    assert locked["wet"] == pytest.approx(c[0] * (1 - math.exp(-c[1])) - c[2])  # s = 1
    assert at_slip["wet"] == pytest.approx(sfc_over_dry["wet"])  # the tabulated wet road's SFC is mu(sin 20 deg)
    assert sfc_over_dry["ratio"] < peak["ratio"], "the sliding test wheel reads less than the peak"
    assert all(0.6 < r["ratio"] < 0.7 for r in (peak, locked, at_slip, sfc_over_dry))
