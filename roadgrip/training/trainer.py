"""A seeded trainer with early stopping on a validation set. It sees a torch module and arrays, nothing else."""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from roadgrip.validation import bounded, check_bounds


@dataclass(frozen=True)
class TrainConfig:
    max_epochs: int = field(default=100, metadata=bounded(1, 10000))
    batch_size: int = field(default=64, metadata=bounded(1, 1 << 20))
    learning_rate: float = field(default=2e-3, metadata=bounded(0.0, 1.0, low_open=True))
    weight_decay: float = field(default=1e-4, metadata=bounded(0.0, 1.0))
    patience: int = field(default=15, metadata=bounded(1, 10000))
    seed: int = 0

    def __post_init__(self):
        check_bounds(self)


@dataclass
class TrainResult:
    best_val_rmse: float
    best_epoch: int
    epochs_run: int
    history: list[dict]


class Trainer:
    """Adam on the mean squared error; keeps the weights of the epoch with the lowest validation RMSE."""

    def __init__(self, config: TrainConfig = TrainConfig()):
        self.config = config

    def fit(
        self, model: nn.Module, x_train: np.ndarray, y_train: np.ndarray, x_val: np.ndarray, y_val: np.ndarray
    ) -> TrainResult:
        cfg = self.config
        if len(x_train) == 0 or len(x_val) == 0:
            raise ValueError(
                f"training needs samples on both sides, got {len(x_train)} train and {len(x_val)} validation"
            )
        torch.manual_seed(cfg.seed)
        generator = torch.Generator().manual_seed(cfg.seed)
        xt, yt = torch.as_tensor(x_train, dtype=torch.float32), torch.as_tensor(y_train, dtype=torch.float32)
        xv, yv = torch.as_tensor(x_val, dtype=torch.float32), torch.as_tensor(y_val, dtype=torch.float32)
        optimizer = torch.optim.Adam(model.parameters(), lr=cfg.learning_rate, weight_decay=cfg.weight_decay)
        best = (math.inf, 0, copy.deepcopy(model.state_dict()))
        history = []
        epoch = 0
        for epoch in range(1, cfg.max_epochs + 1):
            model.train()
            order = torch.randperm(len(xt), generator=generator)
            total = 0.0
            for start in range(0, len(xt), cfg.batch_size):
                idx = order[start : start + cfg.batch_size]
                optimizer.zero_grad()
                loss = torch.mean((model(xt[idx]) - yt[idx]) ** 2)
                loss.backward()
                optimizer.step()
                total += loss.item() * len(idx)
            val_rmse = rmse_of(model, xv, yv)
            history.append({"epoch": epoch, "train_rmse": math.sqrt(total / len(xt)), "val_rmse": val_rmse})
            if val_rmse < best[0]:
                best = (val_rmse, epoch, copy.deepcopy(model.state_dict()))
            elif epoch - best[1] >= cfg.patience:
                break
        model.load_state_dict(best[2])
        model.eval()
        return TrainResult(best_val_rmse=best[0], best_epoch=best[1], epochs_run=epoch, history=history)


def predict(model: nn.Module, x: np.ndarray | torch.Tensor, batch_size: int = 4096) -> np.ndarray:
    model.eval()
    x = torch.as_tensor(x, dtype=torch.float32)
    with torch.no_grad():
        return (
            np.concatenate([model(x[i : i + batch_size]).numpy() for i in range(0, len(x), batch_size)])
            if len(x)
            else np.zeros(0, dtype=np.float32)
        )


def rmse_of(model: nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    return float(np.sqrt(np.mean((predict(model, x) - y.numpy()) ** 2)))
