import pickle

import numpy as np
import pytest
import torch

from roadgrip.models.registry import build_model, model_config
from roadgrip.training.checkpoint import load_checkpoint, save_checkpoint
from roadgrip.training.trainer import TrainConfig, Trainer, predict


def _data(seed=0):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(120, 10, 4)).astype(np.float32)
    y = (0.5 + 0.1 * x[:, -1, 0]).astype(np.float32)
    return x, y


def _train(seed):
    x, y = _data()
    torch.manual_seed(seed)
    model = build_model("sa-cnn-lstm", model_config("sa-cnn-lstm", 4, 10))
    result = Trainer(TrainConfig(max_epochs=5, seed=seed)).fit(model, x[:100], y[:100], x[100:], y[100:])
    return model, result


def test_training_is_seeded():
    a, ra = _train(3)
    b, rb = _train(3)
    assert ra.history == rb.history
    x, _ = _data()
    assert np.array_equal(predict(a, x), predict(b, x))


def test_early_stopping_keeps_the_best_epoch():
    _, result = _train(0)
    best = min(h["val_rmse"] for h in result.history)
    assert result.best_val_rmse == best
    assert result.history[result.best_epoch - 1]["val_rmse"] == best


def test_a_saved_model_reloads_and_predicts_the_same(tmp_path):
    model, _ = _train(1)
    config = model_config("sa-cnn-lstm", 4, 10)
    path = save_checkpoint(tmp_path / "m.pt", "sa-cnn-lstm", config, model, {"feature_set": "x", "mean": np.ones(3)})
    torch.load(path, weights_only=True)  # the file is plain containers and tensors
    loaded, name, meta = load_checkpoint(path)
    x, _ = _data(5)
    assert name == "sa-cnn-lstm" and meta["mean"] == [1.0, 1.0, 1.0]
    assert np.array_equal(predict(model, x), predict(loaded, x))


class _Exploit:
    def __reduce__(self):
        return (exec, ("import pathlib; pathlib.Path('PWNED').write_text('ran')",))


def test_a_model_file_with_code_in_it_is_refused_and_not_run(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = tmp_path / "evil.pt"
    torch.save({"format": "roadgrip-model-v1", "payload": _Exploit()}, path)
    with pytest.raises(ValueError, match="not a roadgrip model file that loads safely"):
        load_checkpoint(path)
    assert not (tmp_path / "PWNED").exists()
    (tmp_path / "plain.pt").write_bytes(pickle.dumps({"format": "other"}))
    with pytest.raises(ValueError):
        load_checkpoint(tmp_path / "plain.pt")
