"""Scenarios from a YAML file, so that a run can be described without writing Python.

```yaml
runs:
  - run_id: wet-patch-braking        # required, unique
    duration_s: 30                   # default 40
    vehicle: paper-suv               # a shipped vehicle's name, or a full profile mapping (CONTRACTS 3.2 fields)
    tire: {model: magic-formula, shape_c: 1.4}   # dugoff | magic-formula | burckhardt (+ that model's parameters)
    road: {kind: straight, length_m: 1500}       # or {kind: circle, radius_m: 200, arc_length_m: 1200}
                                                 # or {kind: polyline, points_m: [[0, 0], [500, 0], [900, 200]]}
    mu: 0.8                          # uniform, or {stations_m: [...], mu_left: [...], mu_right: [...], mode: step|linear}
    speed: {times_s: [0, 10, 14, 30], speeds_mps: [0, 25, 0, 0]}   # optional acc_active: [false, ...]
    steer: {start_s: 5, end_s: 25, amplitude_rad: 0.03, frequency_hz: 0.5}   # optional open-loop steering
    abs_enabled: true
    tcs_enabled: true
    seed: 1
    condition: wet-patch              # labels written into the dataset
    manoeuvre: braking
    grade: 0.03                      # optional, rad, positive uphill; or {stations_m: [...], grade_rad: [...]} (linear)
    effects: production              # optional production-terminal effects: off (default) | production | a mapping of
                                     # ProductionEffects fields (roadgrip/sim/production.py), the others off
```

Every mapping is checked: an unknown key, a missing required key or an impossible value raises ValueError or TypeError
naming the run, the key and the value.
"""

from __future__ import annotations

from pathlib import Path as FilePath

import yaml

from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import GradeProfile, MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.validation import from_mapping
from roadgrip.vehicle.params import VehicleParams, vehicle_by_name
from roadgrip.vehicle.tires import tire_model_by_name

RUN_KEYS = {
    "run_id",
    "duration_s",
    "vehicle",
    "tire",
    "road",
    "mu",
    "speed",
    "steer",
    "abs_enabled",
    "tcs_enabled",
    "seed",
    "condition",
    "manoeuvre",
    "grade",
    "effects",
}
ROAD_KINDS = {
    "straight": ({"length_m"}, lambda r: Path.straight(r["length_m"], r.get("heading_rad", 0.0)), {"heading_rad"}),
    "circle": (
        {"radius_m", "arc_length_m"},
        lambda r: Path.circle(r["radius_m"], r["arc_length_m"], left=r.get("left", True)),
        {"left"},
    ),
    "polyline": ({"points_m"}, lambda r: Path(r["points_m"]), set()),
}


def _keys(where: str, data, required: set, optional: set) -> dict:
    if not isinstance(data, dict):
        raise TypeError(f"{where} must be a mapping, got {data!r}")
    unknown = sorted(set(data) - required - optional)
    if unknown:
        raise ValueError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(required | optional)}")
    missing = sorted(required - set(data))
    if missing:
        raise ValueError(f"{where}: missing key(s) {missing}")
    return data


def _road(where: str, data) -> Path:
    kind = data.get("kind") if isinstance(data, dict) else None
    if kind not in ROAD_KINDS:
        raise ValueError(f"{where}.road.kind must be one of {sorted(ROAD_KINDS)}, got {kind!r}")
    required, build, optional = ROAD_KINDS[kind]
    return build(_keys(f"{where}.road", data, required | {"kind"}, optional))


def _mu(where: str, data) -> MuProfile:
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        return MuProfile.uniform(float(data))
    data = _keys(f"{where}.mu", data, {"stations_m", "mu_left"}, {"mu_right", "mode"})
    return MuProfile(
        data["stations_m"], data["mu_left"], data.get("mu_right", data["mu_left"]), data.get("mode", "step")
    )


def _grade(where: str, data) -> GradeProfile:
    if isinstance(data, (int, float)) and not isinstance(data, bool):
        return GradeProfile.uniform(float(data))
    data = _keys(f"{where}.grade", data, {"stations_m", "grade_rad"}, set())
    return GradeProfile(data["stations_m"], data["grade_rad"])


def _effects(where: str, data) -> ProductionEffects:
    if data == "off":
        return ProductionEffects.off()
    if data == "production":
        return ProductionEffects.production()
    if isinstance(data, dict):
        return from_mapping(ProductionEffects, data)
    raise ValueError(
        f"{where}.effects must be 'off', 'production' or a mapping of ProductionEffects fields, got {data!r}"
    )


def scenario_from_dict(data) -> Scenario:
    run_id = data.get("run_id") if isinstance(data, dict) else None
    where = f"run {run_id!r}"
    data = _keys(where, data, {"run_id", "road", "mu", "speed"}, RUN_KEYS)
    vehicle = data.get("vehicle", "paper-suv")
    vehicle = vehicle_by_name(vehicle) if isinstance(vehicle, str) else VehicleParams.from_dict(vehicle)
    tire = dict(data.get("tire", {"model": "dugoff"}))
    speed = _keys(f"{where}.speed", data["speed"], {"times_s", "speeds_mps"}, {"acc_active"})
    steer = data.get("steer")
    options = {
        k: data[k] for k in ("duration_s", "abs_enabled", "tcs_enabled", "seed", "condition", "manoeuvre") if k in data
    }
    return Scenario(
        run_id=str(run_id),
        path=_road(where, data["road"]),
        mu=_mu(where, data["mu"]),
        speed=SpeedProfile(speed["times_s"], speed["speeds_mps"], speed.get("acc_active")),
        vehicle=vehicle,
        tire=tire_model_by_name(tire.pop("model", "dugoff"), **tire),
        steer=None if steer is None else from_mapping(SteerInput, steer),
        road=data["road"]["kind"],
        grade=_grade(where, data["grade"]) if "grade" in data else GradeProfile.flat(),
        effects=_effects(where, data.get("effects", "off")),
        **options,
    )


def load_scenarios(path: str | FilePath) -> list[Scenario]:
    """All runs of a scenario file, every one checked before any is simulated."""
    text = FilePath(path).read_text()
    data = yaml.safe_load(text)
    data = _keys(f"scenario file {path}", data, {"runs"}, set())
    if not isinstance(data["runs"], list) or not data["runs"]:
        raise ValueError(f"scenario file {path}: 'runs' must be a non-empty list")
    return [scenario_from_dict(run) for run in data["runs"]]
