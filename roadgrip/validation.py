"""Checks for parameter objects: errors that name the field, the constraint and the value received."""

import dataclasses
import math


def bounded(low, high, *, low_open=False, doc=""):
    """Field metadata: the value must lie in [low, high] (or (low, high] with low_open)."""
    return {"bounds": (low, high, low_open), "doc": doc}


def check_bounds(obj):
    """Raise ValueError for the first numeric field of a dataclass outside the bounds in its metadata."""
    owner = type(obj).__name__
    for f in dataclasses.fields(obj):
        if "bounds" not in f.metadata:
            continue
        value = getattr(obj, f.name)
        low, high, low_open = f.metadata["bounds"]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise TypeError(f"{owner}.{f.name} must be a number, got {value!r}")
        if not math.isfinite(value):
            raise ValueError(f"{owner}.{f.name} must be finite, got {value!r}")
        too_low = value <= low if low_open else value < low
        if too_low or value > high:
            bracket = "(" if low_open else "["
            raise ValueError(f"{owner}.{f.name} must be in {bracket}{low}, {high}], got {value!r}")


def check_choice(owner, name, value, choices):
    if value not in choices:
        raise ValueError(f"{owner}.{name} must be one of {sorted(choices)}, got {value!r}")


def from_mapping(cls, data, nested=None):
    """Build dataclass `cls` from a mapping; unknown keys are an error, naming the key."""
    if not isinstance(data, dict):
        raise TypeError(f"{cls.__name__} expects a mapping, got {type(data).__name__}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(data) - names)
    if unknown:
        raise ValueError(f"unknown {cls.__name__} key(s) {unknown}; allowed: {sorted(names)}")
    kwargs = dict(data)
    for key, sub_cls in (nested or {}).items():
        if key in kwargs and not isinstance(kwargs[key], sub_cls):
            kwargs[key] = from_mapping(sub_cls, kwargs[key])
    return cls(**kwargs)
