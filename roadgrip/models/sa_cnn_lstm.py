"""SA-CNN-LSTM (paper 4.1-4.3): self-attention over the window (eq. 10), two 1-D convolutions and a max-pool (eq. 11), an
LSTM (eq. 12) and a dense head."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn


@dataclass(frozen=True)
class SACNNLSTMConfig:
    n_features: int
    window: int
    d_attention: int = 16
    channels: tuple[int, int] = (32, 32)
    kernel: int = 3
    lstm_hidden: int = 32
    dropout: float = 0.1
    output_range: tuple[float, float] | None = None  # bounded output activation lo + (hi - lo) sigmoid(z), or none


class SelfAttention(nn.Module):
    """Eq. 10: Q = X W^q, K = X W^k, V = X W^v, Attention = softmax(Q K^T / sqrt(d_k)) V, over the time steps."""

    def __init__(self, n_features: int, d: int):
        super().__init__()
        self.q, self.k, self.v = (nn.Linear(n_features, d, bias=False) for _ in range(3))
        self.scale = 1.0 / math.sqrt(d)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        q, k, v = self.q(x), self.k(x), self.v(x)  # (B, T, d)
        weights = torch.softmax(q @ k.transpose(1, 2) * self.scale, dim=-1)  # (B, T, T)
        return weights @ v  # (B, T, d)


class SACNNLSTM(nn.Module):
    def __init__(self, config: SACNNLSTMConfig):
        super().__init__()
        c1, c2 = config.channels
        pad = config.kernel // 2
        self.attention = SelfAttention(config.n_features, config.d_attention)
        self.conv = nn.Sequential(
            nn.Conv1d(config.n_features + config.d_attention, c1, config.kernel, padding=pad),
            nn.ReLU(),
            nn.Conv1d(c1, c2, config.kernel, padding=pad),
            nn.ReLU(),
            nn.MaxPool1d(2),
        )
        self.lstm = nn.LSTM(c2, config.lstm_hidden, batch_first=True)
        self.head = nn.Sequential(nn.Dropout(config.dropout), nn.Linear(config.lstm_hidden, 1))
        self.output_range = config.output_range

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        attended = torch.cat([x, self.attention(x)], dim=-1)  # (B, T, F + d): the input and its attended context
        features = self.conv(attended.transpose(1, 2)).transpose(1, 2)  # (B, T/2, C2)
        _, (h, _) = self.lstm(features)  # h: (1, B, H), the state after the last step
        z = self.head(h[-1]).squeeze(-1)
        if self.output_range is None:
            return z
        low, high = self.output_range
        return low + (high - low) * torch.sigmoid(z)


@dataclass(frozen=True)
class BoundedSACNNLSTMConfig(SACNNLSTMConfig):
    """SA-CNN-LSTM whose output activation keeps it in the allowed range (the simple alternative to Q-learning)."""

    output_range: tuple[float, float] | None = (0.0, 1.2)
