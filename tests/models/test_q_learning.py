import re

import numpy as np
import pytest
import torch
from torch import nn

from roadgrip.models.q_learning import (
    ACTIONS,
    QConfig,
    QRefiner,
    _AffineHead,
    clip,
    output_layer,
    penultimate,
    q_update,
    range_metrics,
    refine_model,
)
from roadgrip.models.registry import PAPER_MODELS, build_model, model_config
from roadgrip.training.trainer import predict


def _linear_head(seed=0, n=2000, d=8, noise=0.05, stretch=1.0, shift=0.0, mu_low=0.05, mu_high=1.15):
    """Features h whose first column carries mu with `noise`, the least-squares head (w, b) on them, then its output
    stretched about its mean by `stretch` and moved by `shift` (mu)."""
    rng = np.random.default_rng(seed)
    h = rng.normal(size=(n, d))
    y = rng.uniform(mu_low, mu_high, n)
    h[:, 0] = y + noise * rng.normal(size=n)
    coef, *_ = np.linalg.lstsq(np.c_[h, np.ones(n)], y, rcond=None)
    w, b = coef[None, :d], coef[d]
    mean = float(np.mean(h @ w[0] + b))
    return h, y, stretch * w, np.array([stretch * b + (1 - stretch) * mean + shift])


def test_eq13_update_on_a_hand_computed_case():
    q = np.array([[0.0, 0.5], [0.2, 1.0]])
    # 0.5 + 0.1 (0.3 + 0.9 max(0.2, 1.0) - 0.5) = 0.57
    assert q_update(q, 0, 1, 0.3, 1, beta=0.1, gamma=0.9) == pytest.approx(0.57)
    assert q[0, 1] == pytest.approx(0.57) and q[1].tolist() == [0.2, 1.0] and q[0, 0] == 0.0
    # terminal: no bootstrap, 0.57 + 0.5 (-0.1 - 0.57) = 0.235
    assert q_update(q, 0, 1, -0.1, None, beta=0.5, gamma=0.9, terminal=True) == pytest.approx(0.235)


def test_fast_head_metrics_match_direct_computation():
    rng = np.random.default_rng(1)
    z, y = rng.normal(size=500), rng.uniform(0.0, 1.2, 500)
    head = _AffineHead(z, y, (0.0, 1.2))
    for k, c in [(1.0, 0.5), (0.3, 0.6), (2.5, -0.1), (0.7, 1.3)]:
        fast, direct = head.metrics(k, c), range_metrics(k * z + c, y, (0.0, 1.2))
        assert (fast.n_below, fast.n_above) == (direct.n_below, direct.n_above)
        assert fast.rmse == pytest.approx(direct.rmse, rel=1e-9)
        assert fast.mean_excess == pytest.approx(direct.mean_excess, rel=1e-9, abs=1e-12)


def test_narrow_and_widen_keep_the_mean_and_undo_each_other():
    h, y, w, b = _linear_head()
    refiner = QRefiner()
    head = _AffineHead(h @ w[0], y, refiner.config.allowed_range)
    narrowed = refiner._act(ACTIONS.index("narrow"), (1.0, b[0]), head)
    assert head.mean_prediction(*narrowed) == pytest.approx(head.mean_prediction(1.0, b[0]))
    assert narrowed[0] == pytest.approx(1.0 - refiner.config.scale_step)
    assert refiner._act(ACTIONS.index("widen"), narrowed, head) == pytest.approx((1.0, b[0]))


@pytest.mark.parametrize("stretch, shift", [(1.5, 0.15), (1.6, -0.2)])
def test_refiner_brings_a_misscaled_head_into_range_and_recovers_accuracy(stretch, shift):
    # Output stretched by 1.5-1.6 and shifted by 0.15-0.2: 25-33 % of predictions outside [0, 1.2], RMSE 0.22-0.29.
    h, y, w, b = _linear_head(stretch=stretch, shift=shift)
    result = QRefiner(QConfig(seed=0)).fit(h, y, w, b)
    before, after = result.before, result.after
    assert before.share_out_of_range > 0.2
    assert after.share_out_of_range <= 0.1 * before.share_out_of_range  # seen: <= 0.25 %
    assert after.rmse <= 0.06  # the head's own noise is 0.05; seen: 0.050
    assert after.rmse < range_metrics(clip(h @ w[0] + b[0]), y).rmse  # clipping alone keeps the stretch: 0.16-0.20
    assert np.allclose(h @ result.w.T + result.b, h @ w.T * (result.w[0, 0] / w[0, 0]) + result.b)  # w stays parallel


def test_on_an_accurate_head_it_trades_little_accuracy_for_range():
    # Targets over the whole range [0, 1.2] and prediction noise 0.05: a few percent fall just outside.
    h, y, w, b = _linear_head(mu_low=0.0, mu_high=1.2)
    result = QRefiner(QConfig(seed=0)).fit(h, y, w, b)
    cfg = QConfig()
    assert result.before.share_out_of_range > 0.01
    assert result.after.share_out_of_range <= 0.5 * result.before.share_out_of_range  # seen: 2.8 % -> 0.6 %
    assert result.after.rmse <= 1.2 * result.before.rmse  # seen: +14 %
    assert cfg.objective(result.after) <= cfg.objective(result.before)


def test_a_head_already_in_range_and_accurate_comes_back_unchanged():
    h, y, w, b = _linear_head(noise=0.01)
    result = QRefiner().fit(h, y, w, b)
    assert result.found_in == "trained layer" and result.actions == ()
    assert np.array_equal(result.w, w) and np.array_equal(result.b, b)


def test_the_returned_actions_lead_to_the_returned_layer():
    h, y, w, b = _linear_head(stretch=1.5, shift=0.15)
    refiner = QRefiner(QConfig(seed=2))
    result = refiner.fit(h, y, w, b)
    head = _AffineHead(h @ w[0], y, refiner.config.allowed_range)
    params = (1.0, b[0])
    for name in result.actions:
        params = refiner._act(ACTIONS.index(name), params, head)
    assert np.allclose(params[0] * w, result.w) and params[1] == pytest.approx(result.b[0])
    assert len(result.history) == refiner.config.episodes
    assert result.q_table.shape == (refiner.config.n_states, len(ACTIONS))


def test_same_seed_same_result():
    h, y, w, b = _linear_head(stretch=1.4, shift=-0.1)
    first, second = (QRefiner(QConfig(seed=7, episodes=50)).fit(h, y, w, b) for _ in range(2))
    assert np.array_equal(first.w, second.w) and np.array_equal(first.b, second.b)
    assert np.array_equal(first.q_table, second.q_table)
    assert first.history == second.history and first.actions == second.actions
    other = QRefiner(QConfig(seed=8, episodes=50)).fit(h, y, w, b)
    assert not np.array_equal(first.q_table, other.q_table)


@pytest.mark.parametrize("name", sorted(PAPER_MODELS))
def test_penultimate_times_the_output_layer_is_the_models_prediction(name):
    torch.manual_seed(0)
    model = build_model(name, model_config(name, n_features=9, window=10))
    model.train()
    x = torch.randn(20, 10, 9).numpy()
    layer = output_layer(model)
    assert isinstance(layer, nn.Linear) and layer.out_features == 1
    h = penultimate(model, x, batch_size=8)  # several batches
    assert h.shape == (20, layer.in_features)
    assert model.training, "penultimate restores the training flag"
    w, b = layer.weight.detach().numpy(), layer.bias.detach().numpy()
    np.testing.assert_allclose(h @ w.T[:, 0] + b[0], predict(model, x), atol=1e-5)


@pytest.mark.parametrize("name", sorted(PAPER_MODELS))
def test_refine_model_writes_the_refined_layer_into_the_model(name):
    torch.manual_seed(0)
    model = build_model(name, model_config(name, n_features=9, window=10))
    x = torch.randn(200, 10, 9).numpy()
    raw = predict(model, x)
    with torch.no_grad():  # move the untrained model's output below the range: mean -0.2 mu
        output_layer(model).bias -= float(raw.mean()) + 0.2
    y = 0.6 + 2.0 * (raw - raw.mean())  # targets that the output follows, in range
    result = refine_model(model, x, y, QConfig(seed=0, episodes=100))
    assert result.before.share_out_of_range > 0.9
    assert result.after.n_out_of_range < result.before.n_out_of_range and result.after.rmse < result.before.rmse
    layer = output_layer(model)
    np.testing.assert_allclose(layer.weight.detach().numpy(), result.w, rtol=1e-6)
    after = range_metrics(predict(model, x), y)
    assert after.n_out_of_range == result.after.n_out_of_range
    assert after.rmse == pytest.approx(result.after.rmse, abs=1e-5)


def test_refine_model_refuses_the_bounded_sa_cnn_lstm():
    model = build_model("sa-cnn-lstm-bounded", model_config("sa-cnn-lstm-bounded", n_features=9, window=10))
    x = torch.randn(50, 10, 9).numpy()
    with pytest.raises(ValueError):
        refine_model(model, x, np.full(50, 0.5), QConfig(seed=0, episodes=5))


def test_refine_model_refuses_an_output_that_is_transformed_after_the_last_linear():
    class Bounded(nn.Module):
        def __init__(self):
            super().__init__()
            self.out = nn.Linear(90, 1)

        def forward(self, x):
            return 1.2 * torch.sigmoid(self.out(x.flatten(1))).squeeze(-1)

    with pytest.raises(ValueError, match="transforms the output of its last nn.Linear"):
        refine_model(Bounded(), np.zeros((4, 10, 9), np.float32), np.full(4, 0.5))


def test_output_layer_needs_a_linear_layer():
    with pytest.raises(ValueError, match="has no nn.Linear"):
        output_layer(nn.Sequential(nn.ReLU()))


def test_clip_bounds_predictions():
    assert clip(np.array([-0.3, 0.5, 1.5])).tolist() == [0.0, 0.5, 1.2]
    assert clip(np.array([-0.3, 0.5, 1.5]), (0.0, 1.0)).tolist() == [0.0, 0.5, 1.0]
    with pytest.raises(ValueError, match=r"allowed_range must be .* got \(1.0, 0.0\)"):
        clip(np.zeros(3), (1.0, 0.0))


@pytest.mark.parametrize(
    "field, value",
    [
        ("beta", 0.0),
        ("beta", 1.5),
        ("gamma", -0.1),
        ("epsilon", 2.0),
        ("epsilon_decay", 0.0),
        ("episodes", 0),
        ("steps", 0),
        ("bias_step", 0.0),
        ("scale_step", 0.6),
        ("share_weight", -1.0),
        ("excess_weight", float("nan")),
        ("allowed_range", (1.2, 0.0)),
        ("allowed_range", (0.0,)),
        ("share_edges", (0.1, 0.01)),
        ("share_edges", (0.0, 0.1)),
    ],
)
def test_bad_config_values_name_the_field_and_value(field, value):
    with pytest.raises(ValueError, match=rf"QConfig\.{field} must .*got {re.escape(repr(value))}"):
        QConfig(**{field: value})


def test_config_checks_across_fields_and_types():
    with pytest.raises(ValueError, match=r"QConfig\.epsilon_min must be <= epsilon \(0.1\), got 0.2"):
        QConfig(epsilon=0.1, epsilon_min=0.2)
    with pytest.raises(ValueError, match="must not all be 0"):
        QConfig(accuracy_weight=0.0, share_weight=0.0, excess_weight=0.0)
    with pytest.raises(TypeError, match=r"QConfig\.episodes must be an int, got 2.5"):
        QConfig(episodes=2.5)


def test_fit_checks_shapes_and_names_the_argument():
    h, y, w, b = _linear_head(n=50)
    with pytest.raises(ValueError, match=r"w must be \(1, 8\)"):
        QRefiner().fit(h, y, w[0], b)
    with pytest.raises(ValueError, match=r"y_val must be \(50,\)"):
        QRefiner().fit(h, y[:-1], w, b)
    with pytest.raises(ValueError, match="h_val must be finite"):
        QRefiner().fit(np.where(h > 2, np.nan, h), y, w, b)
