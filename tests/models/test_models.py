import pytest
import torch

from roadgrip.models.registry import MODELS, SEARCH_BUDGET, SEARCH_SPACES, build_model, model_config
from roadgrip.training.trainer import TrainConfig, Trainer, predict


@pytest.mark.parametrize("name", sorted(MODELS))
def test_every_candidate_maps_windows_to_one_value_each(name):
    assert len(SEARCH_SPACES[name]) == SEARCH_BUDGET, "every architecture gets the same search budget"
    for overrides in SEARCH_SPACES[name]:
        model = build_model(name, model_config(name, n_features=9, window=10, **overrides))
        assert model(torch.randn(5, 10, 9)).shape == (5,)


@pytest.mark.parametrize("name", sorted(MODELS))
@pytest.mark.slow
def test_a_model_overfits_a_tiny_batch(name):
    torch.manual_seed(0)
    x = torch.randn(16, 10, 7)
    y = torch.rand(16)
    model = build_model(name, model_config(name, n_features=7, window=10, dropout=0.0))
    Trainer(TrainConfig(max_epochs=400, batch_size=16, learning_rate=5e-3, weight_decay=0.0, patience=400)).fit(
        model, x.numpy(), y.numpy(), x.numpy(), y.numpy()
    )
    assert float(torch.sqrt(torch.mean((torch.as_tensor(predict(model, x)) - y) ** 2))) < 0.02


def test_registry_rejects_unknown_names_and_keys():
    with pytest.raises(ValueError, match="model.name must be one of"):
        model_config("transformer", 9, 10)
    with pytest.raises(ValueError, match=r"unknown dnn config key\(s\) \['layers'\]"):
        model_config("dnn", 9, 10, layers=3)
