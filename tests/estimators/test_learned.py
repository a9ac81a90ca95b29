import json

import numpy as np
import pytest

from roadgrip.estimators.base import ESTIMATE_SCHEMA
from roadgrip.estimators.learned import LearnedEstimator, default_model_path, load_estimator
from roadgrip.features.windows import segment_ids
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


@pytest.fixture(scope="module")
def run_table():
    table = simulate([s for s in paper_scenarios() if s.run_id == "paper-decreasing-circular-e2"])
    return table


def test_default_model_ships_with_how_it_was_trained():
    estimator = load_estimator("default")
    assert estimator.feature_set == "physics" and estimator.window == 10
    record = json.loads(default_model_path().with_suffix(".json").read_text())
    assert record["command"].startswith("roadgrip train") and "--calibration" in record["command"]
    assert record["training"]["data_seed"] == 0 and record["training"]["preset"] == "generalization-train"
    assert record["interval"]["method"] == "split conformal by utilization bin"


def test_batch_estimates_follow_the_contract(run_table):
    estimator = load_estimator("default")
    out = estimator.estimate_batch(run_table, segment_ids(run_table["run_id"].to_numpy()), PAPER_SUV)
    assert out.schema == ESTIMATE_SCHEMA
    assert out.num_rows == run_table.num_rows - estimator.window + 1, "one estimate per full window"
    mu, lo, hi = (out[c].to_numpy() for c in ("mu", "mu_lower", "mu_upper"))
    assert (lo <= mu).all() and (mu <= hi).all()
    assert out["timestamp_ms"].to_numpy()[0] == run_table["timestamp_ms"].to_numpy()[estimator.window - 1]


@pytest.mark.slow
def test_streaming_gives_the_batch_numbers_and_its_state_survives_a_restart(run_table):
    estimator = load_estimator("default")
    batch = estimator.estimate_batch(run_table, np.zeros(run_table.num_rows), PAPER_SUV).to_pylist()
    state = estimator.start(PAPER_SUV)
    streamed = []
    for k, sample in enumerate(run_table.to_pylist()):
        if k == 200:  # save, throw away, restore: as a service restarting mid-stream
            state = estimator.state_from_dict(json.loads(json.dumps(estimator.state_to_dict(state))))
        estimate = estimator.update(state, sample)
        if estimate is not None:
            streamed.append(estimate.to_dict())
    assert len(streamed) == len(batch)
    for s, b in zip(streamed, batch):
        assert s["timestamp_ms"] == b["timestamp_ms"] and s["excited"] == b["excited"]
        assert s["mu"] == pytest.approx(b["mu"], abs=1e-5)


def test_reset_restarts_the_window(run_table):
    estimator = load_estimator("default")
    state = estimator.start(PAPER_SUV)
    samples = run_table.to_pylist()
    assert [estimator.update(state, s) is None for s in samples[:10]] == [True] * 9 + [False]
    estimator.reset(state)
    assert estimator.update(state, samples[10]) is None


def test_unknown_model_names_are_refused():
    with pytest.raises(ValueError, match="--model must be a model file"):
        load_estimator("ekf-magic")
    with pytest.raises(FileNotFoundError):
        LearnedEstimator.load("missing.pt")


@pytest.mark.slow
def test_a_production_feature_model_streams_the_batch_numbers_across_a_restart(tmp_path):
    """The `production` feature set differences consecutive samples: the estimator keeps the previous sample in its
    state (and through state_to_dict), so that a stream, restarted mid-way, gives the batch's numbers."""
    from roadgrip.sim.presets import generalization_scenarios
    from roadgrip.training.fit import block_split, fit, prepare, save_fitted
    from roadgrip.training.trainer import TrainConfig

    scenarios = generalization_scenarios("test", 0, runs=2)
    table = simulate(scenarios)
    data = prepare(table, "production", vehicles={s.vehicle.name: s.vehicle for s in scenarios})
    fitted = fit("convlstm", data, *block_split(data), train_config=TrainConfig(max_epochs=1))
    estimator = LearnedEstimator.load(save_fitted(tmp_path / "production.pt", fitted, "production", {}))
    run = table.slice(0, 400)
    vehicle = scenarios[0].vehicle
    batch = estimator.estimate_batch(run, np.zeros(run.num_rows), vehicle).to_pylist()
    state = estimator.start(vehicle)
    streamed = []
    for k, sample in enumerate(run.to_pylist()):
        if k == 123:
            state = estimator.state_from_dict(json.loads(json.dumps(estimator.state_to_dict(state))))
        flag = "tcs_active" if k % 2 else "esc_active"
        if not sample[flag]:
            sample.pop(flag)  # optional: absent reads as not acting
        estimate = estimator.update(state, sample)
        if estimate is not None:
            streamed.append(estimate.to_dict())
    assert len(streamed) == len(batch) == run.num_rows - estimator.window + 1
    for s, b in zip(streamed, batch):
        assert s["timestamp_ms"] == b["timestamp_ms"] and s["mu"] == pytest.approx(b["mu"], abs=1e-5)
