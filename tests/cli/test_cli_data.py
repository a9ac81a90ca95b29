import json

import pyarrow.compute as pc
import pytest
from pyarrow.parquet import read_table
from typer.testing import CliRunner

from roadgrip.cli import app
from roadgrip.data.dataset import read_dataset

runner = CliRunner()


def test_simulate_writes_a_dataset_and_is_reproducible(tmp_path):
    for name in ("a", "b"):
        result = runner.invoke(
            app, ["simulate", "--preset", "random", "--runs", "3", "--seed", "7", "--out", str(tmp_path / name)]
        )
        assert result.exit_code == 0, result.output
    assert read_dataset(tmp_path / "a").equals(read_dataset(tmp_path / "b"))
    manifest = json.loads((tmp_path / "a" / "manifest.json").read_text())
    assert manifest["preset"] == "random" and manifest["seed"] == 7 and manifest["runs"] == 3
    assert manifest["rows"] == 3 * 400 and len(manifest["scenarios"]) == 3


def test_bad_input_is_a_clear_error_and_writes_nothing(tmp_path):
    result = runner.invoke(app, ["simulate", "--preset", "carsim", "--out", str(tmp_path / "x")])
    assert result.exit_code == 2
    assert "preset" in result.output and "'carsim'" in result.output
    assert not (tmp_path / "x").exists()


def _paper_runs(condition):
    import pyarrow.compute as pc

    from roadgrip.sim.presets import paper_scenarios
    from roadgrip.sim.simulate import simulate

    table = simulate([s for s in paper_scenarios() if s.condition == condition])
    return (table.filter(pc.equal(table["experiment"], 1)), table.filter(pc.equal(table["experiment"], 2)))


@pytest.mark.slow
def test_estimate_on_a_simulated_run_gives_the_benchmarks_accuracy(tmp_path):
    """The offline command and the benchmark see the same numbers: no skew between training and serving."""
    import numpy as np
    import pyarrow.csv as pacsv

    from roadgrip.data.schema import TELEMETRY_COLUMNS
    from roadgrip.evaluation.metrics import rmse
    from roadgrip.training.fit import block_split, fit, prepare, save_fitted
    from roadgrip.training.trainer import TrainConfig, predict

    train, test = _paper_runs("decreasing")
    data = prepare(train, "terminal")
    fitted = fit("sa-cnn-lstm", data, *block_split(data), {}, TrainConfig(max_epochs=10))
    test_data = prepare(test, "terminal")
    benchmark_pred = predict(fitted.model, fitted.scaler.transform(test_data.windows))
    benchmark_rmse = rmse(benchmark_pred, test_data.targets)
    save_fitted(tmp_path / "m.pt", fitted, "terminal", {})
    pacsv.write_csv(test.select(list(TELEMETRY_COLUMNS)), tmp_path / "run.csv")
    result = runner.invoke(
        app,
        [
            "estimate",
            "--input",
            str(tmp_path / "run.csv"),
            "--model",
            str(tmp_path / "m.pt"),
            "--out",
            str(tmp_path / "est.parquet"),
        ],
    )
    assert result.exit_code == 0, result.output
    estimates = read_table(tmp_path / "est.parquet")
    truth = {
        (v, t): m
        for v, t, m in zip(test["vehicle_id"].to_pylist(), test["timestamp_ms"].to_pylist(), test["mu"].to_pylist())
    }
    by_key = {
        (v, t): m
        for v, t, m in zip(
            estimates["vehicle_id"].to_pylist(), estimates["timestamp_ms"].to_pylist(), estimates["mu"].to_pylist()
        )
    }
    t0 = test["timestamp_ms"].to_numpy()[0] - round(test["t_s"].to_numpy()[0] * 1000)
    keys = [(f"sim-{run}", t0 + round(t * 1000)) for run, t in zip(test_data.runs, test_data.t_s)]
    served = np.array([by_key[k] for k in keys])
    # the command's estimates are the model's with the physics guard on them (estimators/guard.py)
    from roadgrip.estimators.guard import apply_bound, tire_force_bound
    from roadgrip.estimators.learned import LearnedEstimator
    from roadgrip.vehicle.params import PAPER_SUV

    inner = LearnedEstimator.load(tmp_path / "m.pt")
    model = {}
    for vehicle in set(test["vehicle_id"].to_pylist()):
        run = test.filter(pc.equal(test["vehicle_id"], vehicle))
        out = inner.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64))
        rows = np.searchsorted(run["timestamp_ms"].to_numpy(), out["timestamp_ms"].to_numpy())
        for k, t in enumerate(out["timestamp_ms"].to_pylist()):
            model[(vehicle, t)] = [out[c][k].as_py() for c in ("mu", "mu_lower", "mu_upper", "excited")] + [
                run[c][int(rows[k])].as_py() for c in ("accel_lon_mps2", "accel_lat_mps2", "speed_mps")
            ]
    mu, lower, upper, excited, ax, ay, speed = (np.array(c) for c in zip(*(model[k] for k in keys)))
    assert mu == pytest.approx(benchmark_pred, abs=1e-5)
    bound = tire_force_bound(PAPER_SUV, ax, ay, speed)
    guarded, *_ = apply_bound(mu, lower, upper, excited, bound)
    assert served == pytest.approx(guarded, abs=1e-5)
    assert (served >= bound).all()
    assert rmse(benchmark_pred, [truth[k] for k in keys]) == pytest.approx(benchmark_rmse, abs=1e-6)


def test_estimate_reports_bad_input_clearly(tmp_path):
    import pyarrow.csv as pacsv

    from roadgrip.data.schema import TELEMETRY_COLUMNS

    _, test = _paper_runs("low")
    test = test.select(list(TELEMETRY_COLUMNS))
    pacsv.write_csv(test.drop_columns(["yaw_rate_radps"]), tmp_path / "missing.csv")
    result = runner.invoke(
        app, ["estimate", "--input", str(tmp_path / "missing.csv"), "--out", str(tmp_path / "o.csv")]
    )
    assert result.exit_code == 2 and "yaw_rate_radps" in result.output
    assert not (tmp_path / "o.csv").exists()
    speeds = test["speed_mps"].to_numpy().copy()
    speeds[[50, 51]] = float("nan")
    import pyarrow as pa

    nan_table = test.set_column(test.schema.get_field_index("speed_mps"), "speed_mps", pa.array(speeds))
    pacsv.write_csv(nan_table, tmp_path / "nan.csv")
    result = runner.invoke(app, ["estimate", "--input", str(tmp_path / "nan.csv"), "--out", str(tmp_path / "o.csv")])
    assert result.exit_code == 0, result.output
    report = pacsv.read_csv(tmp_path / "o.rejections.csv")
    assert report.num_rows == 2 and all("speed_mps" in r for r in report["reason"].to_pylist())
    kmh = test.set_column(
        test.schema.get_field_index("speed_mps"), "speed_mps", pa.array(test["speed_mps"].to_numpy() * 3.6)
    )
    pacsv.write_csv(kmh, tmp_path / "kmh.csv")
    result = runner.invoke(app, ["estimate", "--input", str(tmp_path / "kmh.csv"), "--out", str(tmp_path / "o2.csv")])
    assert result.exit_code == 2 and "speed_mps" in result.output and "km/h" in result.output


def test_estimate_keeps_the_inputs_time_column(tmp_path):
    import pyarrow.csv as pacsv

    from roadgrip.data.schema import TELEMETRY_COLUMNS

    _, test = _paper_runs("high")
    run = test.filter(pc.equal(test["run_id"], "paper-high-straight-e2"))
    columns = [c for c in TELEMETRY_COLUMNS if c != "timestamp_ms"] + ["t_s"]
    pacsv.write_csv(run.select(columns), tmp_path / "relative.csv")
    result = runner.invoke(
        app,
        ["estimate", "--input", str(tmp_path / "relative.csv"), "--model", "ekf", "--out", str(tmp_path / "est.csv")],
    )
    assert result.exit_code == 0, result.output
    out = pacsv.read_csv(tmp_path / "est.csv")
    assert "t_s" in out.column_names and "timestamp_ms" not in out.column_names
    assert out["t_s"].to_pylist()[:3] == pytest.approx([0.0, 0.1, 0.2])
