"""ConvLSTM baseline (Shi et al., 2015): an LSTM whose gates are convolutions, here over the feature axis of each sample,
so that it learns local patterns across neighbouring signals (the four wheel speeds) and their evolution in time."""

from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class ConvLSTMConfig:
    n_features: int
    window: int
    channels: int = 16
    kernel: int = 3
    hidden: int = 32
    dropout: float = 0.1


class ConvLSTMCell(nn.Module):
    """i, f, o, g = conv([x_t, h_{t-1}]); c_t = f c_{t-1} + i g; h_t = o tanh(c_t), with states shaped (B, C, F)."""

    def __init__(self, in_channels: int, channels: int, kernel: int):
        super().__init__()
        self.channels = channels
        self.gates = nn.Conv1d(in_channels + channels, 4 * channels, kernel, padding=kernel // 2)

    def forward(self, x, state):
        h, c = state
        i, f, o, g = self.gates(torch.cat([x, h], dim=1)).chunk(4, dim=1)
        c = torch.sigmoid(f) * c + torch.sigmoid(i) * torch.tanh(g)
        h = torch.sigmoid(o) * torch.tanh(c)
        return h, c


class ConvLSTM(nn.Module):
    def __init__(self, config: ConvLSTMConfig):
        super().__init__()
        self.cell = ConvLSTMCell(1, config.channels, config.kernel)
        self.head = nn.Sequential(
            nn.Flatten(),
            nn.Linear(config.channels * config.n_features, config.hidden),
            nn.ReLU(),
            nn.Dropout(config.dropout),
            nn.Linear(config.hidden, 1),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        batch, steps, n_features = x.shape
        h = x.new_zeros(batch, self.cell.channels, n_features)
        c = torch.zeros_like(h)
        for t in range(steps):
            h, c = self.cell(x[:, t, None, :], (h, c))  # each sample as a 1-channel signal over the features
        return self.head(h).squeeze(-1)
