"""CNN baseline: two 1-D convolutions over time and a max-pool, then a dense head."""

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class CNNConfig:
    n_features: int
    window: int
    channels: tuple[int, int] = (32, 32)
    kernel: int = 3
    hidden: int = 32
    dropout: float = 0.1


class CNN(nn.Module):
    def __init__(self, config: CNNConfig):
        super().__init__()
        c1, c2 = config.channels
        pad = config.kernel // 2
        self.conv = nn.Sequential(
            nn.Conv1d(config.n_features, c1, config.kernel, padding=pad),
            nn.ReLU(),
            nn.Conv1d(c1, c2, config.kernel, padding=pad),
            nn.ReLU(),
            nn.MaxPool1d(2),
        )
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(c2 * (config.window // 2), config.hidden),
            nn.ReLU(),
            nn.Dropout(config.dropout),
            nn.Linear(config.hidden, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.conv(x.transpose(1, 2))).squeeze(-1)  # (B, T, F) -> (B, F, T) -> (B,)
