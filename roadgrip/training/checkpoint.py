"""Checkpoints: the weights with everything needed to use them (model name and config, feature set, window, scaler,
interval calibration, training metadata), in a file that loads with `torch.load(weights_only=True)`: plain containers and
tensors only, so that loading a model file never executes code."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from torch import nn

from roadgrip.models.registry import build_model, model_config

FORMAT = "roadgrip-model-v1"


def save_checkpoint(path: str | Path, model_name: str, config, model: nn.Module, meta: dict) -> Path:
    payload = {
        "format": FORMAT,
        "model": model_name,
        "config": _plain(dataclasses.asdict(config)),
        "state_dict": {k: v.detach().cpu() for k, v in model.state_dict().items()},
        "meta": _plain(meta),
    }
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(payload, path)
    return path


def load_checkpoint(path: str | Path) -> tuple[nn.Module, str, dict]:
    """(model in eval mode, model name, meta). Refuses files that are not roadgrip checkpoints."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"model file {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # a pickle with code in it, or not a torch file at all
        raise ValueError(f"{path} is not a roadgrip model file that loads safely: {err}") from err
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} checkpoint")
    config = dict(payload["config"])
    n_features, window = config.pop("n_features"), config.pop("window")
    config = {k: tuple(v) if isinstance(v, list) else v for k, v in config.items()}
    model = build_model(payload["model"], model_config(payload["model"], n_features, window, **config))
    model.load_state_dict(payload["state_dict"])
    model.eval()
    return model, payload["model"], payload["meta"]


def _plain(value):
    """JSON-like containers only (tuples become lists), so that weights_only loading accepts them."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if hasattr(value, "tolist"):
        return value.tolist()
    return value
