"""DNN baseline (paper ref. 18): the flattened window through fully connected layers."""

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class DNNConfig:
    n_features: int
    window: int
    hidden: tuple[int, ...] = (64, 32)
    dropout: float = 0.1


class DNN(nn.Module):
    def __init__(self, config: DNNConfig):
        super().__init__()
        layers, width = [], config.n_features * config.window
        for h in config.hidden:
            layers += [nn.Linear(width, h), nn.ReLU(), nn.Dropout(config.dropout)]
            width = h
        layers.append(nn.Linear(width, 1))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x.flatten(1)).squeeze(-1)  # (B, T, F) -> (B, T*F) -> (B,)
