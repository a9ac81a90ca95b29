"""The physics benchmark end to end on a handful of short runs: the prior baseline is in the table, skill is computed
as defined, and the estimator receives the catalogue profile, not the drawn vehicle."""

import math

import numpy as np
import pytest

from roadgrip.estimators import learned
from roadgrip.evaluation.baseline import PRIOR_NAME, prior_baseline
from roadgrip.evaluation.physics_benchmark import mu_band, physics_markdown, rows_table, run_physics_benchmark
from roadgrip.sim.presets import PHYSICS_MANOEUVRES, PHYSICS_SPLITS, physics_benchmark_runs, preset_scenarios
from roadgrip.vehicle.params import VEHICLES


def test_mu_bands_by_hand():
    assert mu_band([0.1, 0.3, 0.3001, 0.5999, 0.6, 1.2]).tolist() == [
        "<= 0.3",
        "<= 0.3",
        "0.3-0.6",
        "0.3-0.6",
        ">= 0.6",
        ">= 0.6",
    ]


def test_splits_are_fixed_cover_every_surface_and_hold_the_test_vehicle_and_tire_out_of_validation():
    validation = physics_benchmark_runs("validation")
    test = physics_benchmark_runs("test")
    assert [s.run_id for s, _ in validation] == [s.run_id for s, _ in physics_benchmark_runs("validation")]
    assert validation[5][0].vehicle == physics_benchmark_runs("validation")[5][0].vehicle
    for runs in (validation, test):
        assert {s.condition for s, _ in runs} == {"ice", "snow", "wet", "dry"}
        assert {s.manoeuvre for s, _ in runs} == set(PHYSICS_MANOEUVRES)
        mus = np.array([s.mu.mu_left[0] for s, _ in runs])
        assert mus.min() < 0.2 and mus.max() > 0.9
        assert all(entry.name in VEHICLES and s.vehicle.drive == entry.drive for s, entry in runs)
    assert {e.name for _, e in validation}.isdisjoint({e.name for _, e in test})
    assert {s.tire.name for s, _ in validation}.isdisjoint({s.tire.name for s, _ in test})
    assert len(preset_scenarios("physics-test")) == PHYSICS_SPLITS["test"].runs
    with pytest.raises(ValueError, match="fixed per split"):
        preset_scenarios("physics-validation", seed=1)


class _Spy:
    """Wraps a loaded estimator; remembers every (profile, run, estimates) it was called with, and the segment ids."""

    def __init__(self, inner):
        self.inner, self.calls, self.segments = inner, [], []

    def estimate_batch(self, run, segments, vehicle):
        out = self.inner.estimate_batch(run, segments, vehicle)
        self.calls.append((vehicle, run, out))
        self.segments.append(np.asarray(segments))
        return out


def spied_benchmark(**options):
    """run_physics_benchmark("validation", ("pmf",), **options) with pmf wrapped in a _Spy: (rows, the spy)."""
    real = learned.load_estimator
    spies = []

    def load(name):
        spies.append(_Spy(real(name)))
        return spies[-1]

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(learned, "load_estimator", load)
        rows = run_physics_benchmark("validation", estimators=("pmf",), **options)
    return rows, spies[0]


@pytest.fixture(scope="module")
def spied_run():
    return spied_benchmark(runs=4)  # the first four runs: braking, accelerating, ramp and sine steering on ice


def test_the_estimator_receives_the_catalogue_profile_not_the_drawn_vehicle(spied_run):
    _, spy = spied_run
    drawn = {s.run_id: (s.vehicle, entry) for s, entry in physics_benchmark_runs("validation", 4)}
    assert len(spy.calls) == 4
    for profile, run, _ in spy.calls:
        vehicle, entry = drawn[run["run_id"][0].as_py()]
        assert profile.mass_kg == entry.mass_kg != vehicle.mass_kg
        assert profile.wheel_radius_m == entry.wheel_radius_m != vehicle.wheel_radius_m
        assert profile.tire_front == entry.tire_front != vehicle.tire_front
        assert profile.drive == vehicle.drive


def test_the_prior_baseline_comes_first_with_no_skill_of_its_own(spied_run):
    rows, _ = spied_run
    assert rows[0]["estimator"] == PRIOR_NAME
    prior = [r for r in rows if r["estimator"] == PRIOR_NAME and r["n"]]
    assert prior and all(r["skill"] == 0.0 for r in prior)
    base = prior_baseline()
    whole = next(r for r in prior if (r["manoeuvre"], r["band"], r["bin"]) == ("all", "all", "all"))
    assert whole["n"] == 4 * 300  # every sample of four 30 s runs at 10 Hz
    assert whole["width"] == pytest.approx(base.mu_upper - base.mu_lower)
    table = physics_markdown(rows)
    assert "| prior | all |" in table and "| pmf | all |" in table
    assert "| prior | ramp_steer |" in table and "| pmf | braking_abs |" in table
    # the bound is the one the handed profile proves, which the guard enforces: a guarded estimator is never below it
    assert all(r["below_bound"] == 0.0 for r in rows if r["estimator"] == "pmf" and r["n"])


def test_skill_and_coverage_of_one_cell_by_hand(spied_run):
    rows, spy = spied_run
    truth, mu, lower, upper = [], [], [], []
    for _, run, out in spy.calls:
        at = np.searchsorted(run["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
        truth.append(run["mu"].to_numpy()[at])
        mu.append(out["mu"].to_numpy())
        lower.append(out["mu_lower"].to_numpy())
        upper.append(out["mu_upper"].to_numpy())
    truth, mu, lower, upper = (np.concatenate(a) for a in (truth, mu, lower, upper))
    assert truth.max() <= 0.2  # the first four runs are on ice: the <= 0.3 band is every sample
    rmse_est = math.sqrt(np.mean((mu - truth) ** 2))
    rmse_prior = math.sqrt(np.mean((prior_baseline().mu_median - truth) ** 2))
    key = ("pmf", "all", "<= 0.3", "all")
    cell = next(r for r in rows if (r["estimator"], r["manoeuvre"], r["band"], r["bin"]) == key)
    assert cell["n"] == truth.size
    assert cell["rmse"] == pytest.approx(rmse_est)
    assert cell["skill"] == pytest.approx(1.0 - rmse_est / rmse_prior)
    assert cell["coverage"] == pytest.approx(np.mean((truth >= lower) & (truth <= upper)))


def test_rows_table_keeps_every_column_of_any_row():
    table = rows_table([{"bin": "< 0.3", "n": 0}, {"bin": "ABS", "n": 3, "rmse": 0.1}])
    assert table.column_names == ["bin", "n", "rmse"]
    assert table["rmse"].to_pylist() == [None, 0.1]


@pytest.mark.parametrize(
    ("args", "message"), [(["--split", "training"], "'training'"), (["--seed", "3"], "fixed per split")]
)
def test_evaluate_physics_refuses_an_unknown_split_and_a_seed(tmp_path, args, message):
    from typer.testing import CliRunner

    from roadgrip.cli import app

    result = CliRunner().invoke(app, ["evaluate", "--benchmark", "physics", "--out", str(tmp_path / "x"), *args])
    assert result.exit_code == 2, result.output
    assert message in result.output
    assert not (tmp_path / "x").exists()


def test_manoeuvre_rows_split_the_samples_of_the_whole(spied_run):
    rows, spy = spied_run
    per_run = {run["run_id"][0].as_py(): out.num_rows for _, run, out in spy.calls}
    cells = [r for r in rows if r["estimator"] == "pmf" and r["manoeuvre"] != "all" and r["band"] == "<= 0.3"]
    assert [r["manoeuvre"] for r in cells] == ["braking_abs", "acceleration", "ramp_steer", "sine_steer"]
    assert [r["n"] for r in cells] == list(per_run.values())


def test_the_base_channel_set_is_the_benchmark_without_channels_and_sets_are_named():
    plain = run_physics_benchmark("validation", ("pmf",), runs=2)
    by_set = run_physics_benchmark("validation", ("pmf",), runs=2, channels=("base", "gnss"))
    assert {r["estimator"] for r in by_set} == {PRIOR_NAME, "pmf [base]", "pmf [gnss]"}
    base = [r | {"estimator": "pmf"} for r in by_set if r["estimator"] == "pmf [base]"]
    assert base == [r for r in plain if r["estimator"] == "pmf"]
    with pytest.raises(ValueError, match="channels"):
        run_physics_benchmark("validation", ("pmf",), runs=1, channels=("radar",))


def test_a_calibrated_car_reads_its_lead_in_first_and_is_scored_on_the_run_alone():
    """With a lead-in the estimator gets, per run, the lead-in's rows (segment 0), ending LEAD_IN_GAP_S before the run,
    then the run's (segment 1: a new trip); the cells count the run's samples only, under `<estimator> calibrated`."""
    from roadgrip.evaluation.bins import LEAD_IN_GAP_S

    rows, spy = spied_benchmark(runs=2, lead_in_s=20.0)
    assert {r["estimator"] for r in rows} == {PRIOR_NAME, "pmf calibrated"}
    whole = next(
        r for r in rows if (r["estimator"], r["manoeuvre"], r["band"], r["bin"]) == ("pmf calibrated",) + ("all",) * 3
    )
    assert whole["n"] == 2 * 300
    for (_, data, out), segments in zip(spy.calls, spy.segments):
        assert segments.tolist() == [0] * 200 + [1] * 300
        ids = data["run_id"].to_pylist()
        assert ids[:200] == [ids[-1] + "-lead-in"] * 200 and ids[200:] == [ids[-1]] * 300
        ts = data["timestamp_ms"].to_numpy()
        assert (np.diff(ts) > 0).all()
        assert ts[200] - ts[199] == LEAD_IN_GAP_S * 1000.0
        assert out.num_rows == 500
