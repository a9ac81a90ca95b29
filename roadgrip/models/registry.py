"""Models by name, with their config classes and the hyperparameter search space each gets in a benchmark.

Every architecture gets the same search budget: SEARCH_BUDGET candidate configs, from small to large."""

from __future__ import annotations

import dataclasses

from torch import nn

from roadgrip.models.cnn import CNN, CNNConfig
from roadgrip.models.convlstm import ConvLSTM, ConvLSTMConfig
from roadgrip.models.dnn import DNN, DNNConfig
from roadgrip.models.sa_cnn_lstm import SACNNLSTM, BoundedSACNNLSTMConfig, SACNNLSTMConfig
from roadgrip.validation import check_choice

MODELS = {
    "dnn": (DNNConfig, DNN),
    "cnn": (CNNConfig, CNN),
    "convlstm": (ConvLSTMConfig, ConvLSTM),
    "sa-cnn-lstm": (SACNNLSTMConfig, SACNNLSTM),
    "sa-cnn-lstm-bounded": (BoundedSACNNLSTMConfig, SACNNLSTM),
}
PAPER_MODELS = ("dnn", "cnn", "convlstm", "sa-cnn-lstm")  # the architectures of the paper's tables
DISPLAY_NAMES = {
    "dnn": "DNN",
    "cnn": "CNN",
    "convlstm": "ConvLSTM",
    "sa-cnn-lstm": "SA-CNN-LSTM",
    "sa-cnn-lstm-bounded": "SA-CNN-LSTM (bounded output)",
}
SEARCH_SPACES = {
    "dnn": [{"hidden": (32, 16)}, {"hidden": (64, 32)}, {"hidden": (128, 64)}],
    "cnn": [
        {"channels": (16, 16), "hidden": 16},
        {"channels": (32, 32), "hidden": 32},
        {"channels": (64, 64), "hidden": 64},
    ],
    "convlstm": [{"channels": 8, "hidden": 16}, {"channels": 16, "hidden": 32}, {"channels": 32, "hidden": 64}],
    "sa-cnn-lstm": [
        {"d_attention": 8, "channels": (16, 16), "lstm_hidden": 16},
        {"d_attention": 16, "channels": (32, 32), "lstm_hidden": 32},
        {"d_attention": 32, "channels": (64, 64), "lstm_hidden": 64},
    ],
}
SEARCH_SPACES["sa-cnn-lstm-bounded"] = SEARCH_SPACES["sa-cnn-lstm"]
SEARCH_BUDGET = 3


def model_config(name: str, n_features: int, window: int, **overrides):
    check_choice("model", "name", name, set(MODELS))
    config_cls, _ = MODELS[name]
    allowed = {f.name for f in dataclasses.fields(config_cls)} - {"n_features", "window"}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise ValueError(f"unknown {name} config key(s) {unknown}; allowed: {sorted(allowed)}")
    return config_cls(n_features=n_features, window=window, **overrides)


def build_model(name: str, config) -> nn.Module:
    check_choice("model", "name", name, set(MODELS))
    return MODELS[name][1](config)
