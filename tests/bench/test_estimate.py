"""`roadgrip bench estimate` support, and the fusion of a physics and a learned estimate."""

import json

import numpy as np
import pytest
import torch

from roadgrip.bench.estimate import BENCH_CHANNEL_SETS, bench_estimators, format_bench, stream_samples
from roadgrip.estimators.fusion import FusionEstimator, fuse
from roadgrip.estimators.learned import load_estimator
from roadgrip.estimators.physics import physics_estimator
from roadgrip.estimators.vehicle_model import INTERVAL_Z
from roadgrip.evaluation.physics_benchmark import CHANNEL_SETS
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


@pytest.mark.slow
def test_bench_reports_throughput_and_latency_of_each_estimator():  # the figures themselves: docs, not a test
    results = bench_estimators(("ekf", "ukf", "default"), 300)
    assert [r["estimator"] for r in results] == ["ekf", "ukf", "default"]
    for r in results:
        assert set(r) == {
            "estimator",
            "updates",
            "updates_per_s",
            "latency_median_us",
            "latency_p99_us",
            "batch_rows_per_s",
            "threads",
        }
        assert r["updates"] == 300 and r["threads"] == 1
        assert (
            r["updates_per_s"] > 0 and 0 < r["latency_median_us"] <= r["latency_p99_us"] and r["batch_rows_per_s"] > 0
        )
    table = format_bench(results)
    assert "| ekf |" in table and "| default |" in table
    with pytest.raises(ValueError, match="n_updates"):
        bench_estimators(("ekf",), 10)


def test_each_channel_set_streams_only_its_channels_and_gets_a_row():
    """A set's stream carries the channels the physics benchmark's set of that name keeps, and no other (null, as a car
    that does not send them); the base channels are the same in every set; a row per estimator and set."""
    channel_names = {c for names in CHANNEL_SETS.values() for c in names}
    base = None
    for name in BENCH_CHANNEL_SETS:
        samples, _, _ = stream_samples(500, name)
        sent = {c for c in channel_names if any(s[c] is not None for s in samples)}
        assert sent == set(CHANNEL_SETS[name]), name
        common = [{k: v for k, v in s.items() if k not in channel_names} for s in samples]
        base = common if base is None else base
        assert common == base, name
    results = bench_estimators(("pmf",), 100, ("base", "all"))
    assert [r["estimator"] for r in results] == ["pmf [base]", "pmf [all]"]
    assert "| pmf [all] |" in format_bench(results)
    with pytest.raises(ValueError, match="unknown channel set 'radar'"):
        bench_estimators(("pmf",), 100, ("radar",))


def test_fuse_is_inverse_variance_weighting():
    z = INTERVAL_Z
    mu, lower, upper = fuse(0.4, 0.4 - 0.1 * z, 0.4 + 0.1 * z, 0.8, 0.8 - 0.2 * z, 0.8 + 0.2 * z)  # sigma 0.1, 0.2
    assert mu == pytest.approx((0.4 / 0.01 + 0.8 / 0.04) / (1 / 0.01 + 1 / 0.04))
    assert upper - mu == pytest.approx(z / np.sqrt(1 / 0.01 + 1 / 0.04)) and mu - lower == pytest.approx(upper - mu)
    # arrays, and a physics interval clipped at 0: its wider side sets its sigma (0.6 / 1.645), not the clipped one
    mu, _, _ = fuse(np.array([0.3, 0.9]), np.array([0.0, 0.5]), np.array([0.9, 1.3]), 0.6, 0.5, 0.7)
    w_p, w_l = (z / 0.6) ** 2, (z / 0.1) ** 2
    assert mu[0] == pytest.approx((0.3 * w_p + 0.6 * w_l) / (w_p + w_l))
    assert 0.6 < mu[1] < 0.9


@pytest.fixture
def one_torch_thread():
    """Sample-by-sample inference is slowed, not sped up, by threads (all the more beside a training job)."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def test_fusion_streams_what_it_batches_and_restores_its_state(one_torch_thread):
    run = simulate([s for s in paper_scenarios() if s.run_id == "paper-low-circular-e2"]).slice(0, 150)
    fusion = FusionEstimator(physics_estimator("ekf"), load_estimator("default"))
    batch = fusion.estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), PAPER_SUV).to_pylist()
    state = fusion.start(PAPER_SUV)
    streamed = []
    for k, row in enumerate(run.to_pylist()):
        if k == 60:
            state = fusion.state_from_dict(json.loads(json.dumps(fusion.state_to_dict(state))))
        streamed.append(fusion.update(state, row).to_dict())
    assert len(streamed) == len(batch) == run.num_rows
    for s, b in zip(streamed, batch):
        assert s["timestamp_ms"] == b["timestamp_ms"] and s["excited"] == b["excited"]
        assert s["mu"] == pytest.approx(b["mu"], abs=1e-5)
    assert all(r["estimator"] == "fusion" for r in batch)
