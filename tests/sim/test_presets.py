import math

import numpy as np
import pyarrow.compute as pc
import pytest

from roadgrip.data.schema import CHANNEL_NAMES, DATASET_SCHEMA
from roadgrip.sim.presets import PAPER_CONDITIONS, paper_scenarios, preset_scenarios, random_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.units import kmh_to_mps
from roadgrip.vehicle.params import PAPER_SUV


@pytest.fixture(scope="module")
def paper_table():
    return simulate(paper_scenarios(seed=0))


def test_paper_preset_is_the_papers_design():
    scenarios = paper_scenarios()
    assert len(scenarios) == 20
    cases = {(s.condition, s.road, s.experiment) for s in scenarios}
    assert cases == {(c, r, e) for c in PAPER_CONDITIONS for r in ("straight", "circular") for e in (1, 2)}
    for s in scenarios:
        assert s.duration_s == 40.0 and s.n_samples == 400
        assert s.vehicle == PAPER_SUV
        assert s.speed.speeds_mps.max() == pytest.approx(kmh_to_mps(120.0))
        assert s.speed.speeds_mps[0] == 0.0 and s.speed.speeds_mps[-1] == 0.0
    values = {s.condition: s.mu.mu_left.tolist() for s in scenarios}
    assert values == {
        "low": [0.2],
        "medium": [0.5],
        "high": [0.8],
        "increasing": [0.1, 0.3, 0.6, 0.9],
        "decreasing": [0.9, 0.6, 0.3, 0.1],
    }
    seeds = [s.seed for s in scenarios]
    assert len(set(seeds)) == 20, "each experiment has its own seed"


def test_paper_dataset_rows_schema_and_labels(paper_table):
    assert paper_table.schema == DATASET_SCHEMA
    assert paper_table.num_rows == 20 * 400
    t = paper_table["t_s"].to_numpy()
    assert np.allclose(np.diff(t.reshape(20, 400), axis=1), 0.1)
    ts = paper_table["timestamp_ms"].to_numpy().reshape(20, 400)
    assert (np.diff(ts, axis=1) == 100).all()
    for condition, values in PAPER_CONDITIONS.items():
        run = paper_table.filter(pc.equal(paper_table["run_id"], f"paper-{condition}-straight-e2"))
        assert sorted(np.unique(run["mu"].to_numpy())) == sorted(values), "every section of the road is driven over"
    numeric = [f.name for f in DATASET_SCHEMA if f.type in ("double", "int64") and f.name not in CHANNEL_NAMES]
    for name in numeric:
        assert np.isfinite(paper_table[name].to_numpy()).all(), name
    for name in CHANNEL_NAMES:  # the paper's car sends none of the optional channels: null, never zero
        assert paper_table[name].null_count == paper_table.num_rows, name


def test_paper_vehicle_reaches_120_kmh_on_the_high_mu_road(paper_table):
    run = paper_table.filter(pc.equal(paper_table["run_id"], "paper-high-straight-e1"))
    assert run["vx_true_mps"].to_numpy().max() == pytest.approx(kmh_to_mps(120.0), rel=0.02)


def test_decreasing_road_ends_beyond_the_limit_with_abs(paper_table):
    """On the last, 0.1 section the profile asks 1.67 m/s^2 of braking, more than 0.1 g allows: ABS works, the car lags."""
    run = paper_table.filter(pc.equal(paper_table["run_id"], "paper-decreasing-straight-e1"))
    mu = run["mu"].to_numpy()
    on_ice = mu == 0.1
    assert run["abs_active"].to_numpy()[on_ice].any()
    assert -run["ax_true_mps2"].to_numpy()[on_ice].max() < 0.1 * 9.81 * 1.05


def test_same_seed_same_data_other_seed_other_noise():
    a = simulate(paper_scenarios(seed=3)[:2])
    b = simulate(paper_scenarios(seed=3)[:2])
    c = simulate(paper_scenarios(seed=4)[:2])
    assert a.equals(b)
    assert not np.array_equal(a["speed_mps"].to_numpy(), c["speed_mps"].to_numpy())
    assert np.array_equal(a["vx_true_mps"].to_numpy(), c["vx_true_mps"].to_numpy()), "noise differs, physics does not"


def test_random_preset_is_varied_and_reproducible():
    scenarios = random_scenarios(runs=60, seed=11)
    assert [s.run_id for s in scenarios] == [s.run_id for s in random_scenarios(runs=60, seed=11)]
    assert len({s.manoeuvre for s in scenarios}) == 7
    assert len({s.tire.name for s in scenarios}) == 3
    assert len({s.vehicle.drive for s in scenarios}) == 3
    mus = np.concatenate([np.r_[s.mu.mu_left, s.mu.mu_right] for s in scenarios])
    assert mus.min() >= 0.1 and mus.max() <= 1.0
    assert any(not s.abs_enabled for s in scenarios) and any(s.speed.acc_active.any() for s in scenarios)


def test_random_preset_runs_have_no_nan_and_acc_flag_means_acc():
    scenarios = random_scenarios(runs=40, seed=5)
    table = simulate(scenarios)
    for name in ("vx_true_mps", "vy_true_mps", "yaw_rate_true_radps", "fz_fl_n", "speed_mps", "latitude_deg"):
        assert np.isfinite(table[name].to_numpy()).all(), name
    acc = table["acc_active"].to_numpy()
    cruise = np.array([m == "cruise" for m in table["manoeuvre"].to_pylist()])
    assert acc[cruise].all() and not acc[~cruise].any()


def test_preset_errors_name_the_problem():
    with pytest.raises(ValueError, match="preset.*'bogus'"):
        preset_scenarios("bogus")
    with pytest.raises(ValueError, match="exactly 20 runs"):
        preset_scenarios("paper", runs=5)
    with pytest.raises(ValueError, match="runs must be >= 1, got 0"):
        preset_scenarios("random", runs=0)


def test_generalization_presets_hold_out_mu_bands_and_a_vehicle():
    from roadgrip.sim.presets import GENERALIZATION_TEST_MU_BANDS, generalization_scenarios

    def in_bands(mu, bands):
        return any(lo <= mu <= hi for lo, hi in bands)

    train = generalization_scenarios("train", seed=0, runs=60) + generalization_scenarios(
        "calibration", seed=0, runs=20
    )
    test = generalization_scenarios("test", seed=0, runs=20)
    for s in train:
        assert s.mu.mode == "step"
        assert not any(
            lo < m < hi for lo, hi in GENERALIZATION_TEST_MU_BANDS for m in np.r_[s.mu.mu_left, s.mu.mu_right]
        )
        assert not s.vehicle.name.startswith("test")
    for s in test:
        assert s.mu.mode == "step"
        assert all(in_bands(m, GENERALIZATION_TEST_MU_BANDS) for m in np.r_[s.mu.mu_left, s.mu.mu_right])
    assert {round(s.vehicle.wheelbase_m / 2.55, 1) for s in test} == {1.0}, "all around the compact hatchback"
    assert not {s.run_id for s in train} & {s.run_id for s in test}


def test_roundabouts_are_three_quarter_circles_between_straights():
    from roadgrip.sim.presets import ROUNDABOUT_ARC_RAD, ROUNDABOUT_GAP_M, roundabouts

    path = roundabouts(12.0, 300.0)
    pts = path.points_m
    assert path.length_m >= 300.0
    heading = np.unwrap(np.arctan2(*np.diff(pts, axis=0)[:, ::-1].T))
    per_roundabout = ROUNDABOUT_GAP_M + ROUNDABOUT_ARC_RAD * 12.0
    turned = heading[-1] - heading[0]
    assert turned == pytest.approx(math.ceil(300.0 / per_roundabout) * ROUNDABOUT_ARC_RAD, abs=0.1), "left turns only"
    # the ring: every point of the first arc 12 m from its centre (left of the entry)
    ring = pts[2 : 2 + 10]
    assert np.hypot(ring[:, 0] - ROUNDABOUT_GAP_M, ring[:, 1] - 12.0) == pytest.approx(12.0, abs=1e-9)


def test_physics_tight_turns_span_junctions_and_roundabouts():
    from roadgrip.sim.presets import physics_benchmark_runs

    for split in ("validation", "test"):
        turns = [s for s, _ in physics_benchmark_runs(split) if s.manoeuvre == "tight_turn"]
        assert len(turns) == 40
        curvature = []
        kinds = set()
        for s in turns:
            d = np.diff(s.path.points_m, axis=0)
            h = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
            k = np.abs(np.diff(h)) / np.minimum(np.hypot(*d[1:].T), np.hypot(*d[:-1].T))
            curvature.append(k.max())
            kinds.add("roundabout" if np.hypot(*d.T).max() > 20.0 else "circle")  # straights between the rings
        radius = 1.0 / np.array(curvature)
        assert kinds == {"roundabout", "circle"}, split
        assert radius.min() >= 9.9 and radius.max() <= 25.5 and radius.min() < 12.0, split


def test_a_physics_lead_in_is_the_same_car_driving_calmly_on_another_road():
    """The lead-in is the run's car (vehicle, tire, sensors' seed, effects), on a wet or dry road drawn apart from the
    run's, calm throughout: no controller acts and the tires stay under half the road's limit. Its asphalt's
    slope is the run's surface's over that surface's share of it (PHYSICS_SURFACE_SLOPE), where the tire model's slope
    is the same on every surface; Burckhardt's tire (the test split) is the run's as it is."""
    from roadgrip.sim.presets import (
        LEAD_IN_SUFFIX,
        PHYSICS_LEAD_IN_SURFACES,
        PHYSICS_SURFACE_SLOPE,
        physics_benchmark_runs,
        physics_lead_in,
    )

    runs = [s for s, _ in physics_benchmark_runs("validation", 8)]
    leads = [physics_lead_in(s, 120.0) for s in runs]
    for run, lead in zip(runs, leads):
        assert lead.run_id == run.run_id + LEAD_IN_SUFFIX
        assert (lead.vehicle, lead.seed, lead.effects) == (run.vehicle, run.seed, run.effects)
        assert type(lead.tire) is type(run.tire) and not run.tire.slope_by_surface
        low, high = PHYSICS_SURFACE_SLOPE[run.condition]
        assert low <= run.tire.stiffness_scale / lead.tire.stiffness_scale <= high
        assert lead.duration_s == 120.0 and lead.steer is None
        assert PHYSICS_LEAD_IN_SURFACES["wet"][0] <= lead.mu.mu_left[0] <= PHYSICS_LEAD_IN_SURFACES["dry"][1]
    test_run = physics_benchmark_runs("test", 1)[0][0]
    assert physics_lead_in(test_run, 60.0).tire == test_run.tire
    assert len({round(float(lead.mu.mu_left[0]), 6) for lead in leads}) == len(leads)
    table = simulate(leads)
    mu = table["mu"].to_numpy()
    u = np.hypot(table["ax_true_mps2"].to_numpy(), table["ay_true_mps2"].to_numpy()) / (9.81 * mu)
    moving = table["vx_true_mps"].to_numpy() > 1.0  # the last metre of a stop: the driver model stops the car hard
    assert u[moving].max() < 0.5
    assert not any(table[c].to_numpy(zero_copy_only=False).any() for c in ("abs_active", "tcs_active", "esc_active"))
    speed = table["vx_true_mps"].to_numpy()
    assert speed.max() > 15.0 and speed.min() < 0.5  # it cruises and it stops
    assert np.abs(table["ay_true_mps2"].to_numpy()).max() > 0.5  # and it turns
    with pytest.raises(ValueError, match="more than 0 s"):
        physics_lead_in(runs[0], 0.0)
