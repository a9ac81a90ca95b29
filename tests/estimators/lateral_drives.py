"""Simulated steering drives for pmf's lateral channel: a ramp steer and a sine steer at constant speed, on ice and on
dry asphalt, every production-terminal effect on (tire stiffness off the profile's included).

Each drive runs 12 s straight at its speed (calm: the prior's wide interval must stay), then steers open loop:

- ramp: the road-wheel angle rises as the first quarter of a slow sine (0 to the amplitude over 10 s), past the limit
  at its end;
- sine: a 0.25 Hz sine steer of the same amplitude for 12 s.

The amplitude asks for about 1.2 x the road's limit in a steady turn, delta = L / R + K_us a_y with a_y = 1.2 mu g:
the tires work from 0 to past their limit. Before it, the same car (vehicle, tire, road) drives calmly for 80 s along
350 m curves, left then right, at 11 m/s (a_y 0.35 m/s^2: under a quarter of the ice's limit): the calibration a car on
the road has from its earlier driving (`calibrated=False`: a fresh state instead). Curves both ways, since on one curve
the understeer line's offset (steering and gyro bias) and its slope cannot be told apart. `scenarios(split)`: "test" (the test module's, seeds 300-) or "held-out"
(other vehicles, the Burckhardt tire, other seeds: for measuring, never for tuning).
"""

from __future__ import annotations

import functools
import math

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc

from roadgrip.estimators.pmf import PMFEstimator
from roadgrip.sim.driver import SpeedProfile, SteerInput
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires import BurckhardtTire, DugoffTire, MagicFormulaTire

RWD_SEDAN = MIDSIZE_SEDAN.replace(name="midsize-sedan-rwd", drive="rwd", front_drive_share=0.0)
CALM_S = 12.0
STEER_S = 12.0
SPLITS = {
    # (vehicles, tires, ice mu, seed base)
    "test": ((PAPER_SUV, MIDSIZE_SEDAN), (DugoffTire(stiffness_scale=0.8), MagicFormulaTire(stiffness_scale=1.2)), 300),
    "held-out": ((RWD_SEDAN, COMPACT_HATCHBACK), (BurckhardtTire(), MagicFormulaTire(stiffness_scale=0.9)), 700),
}
SURFACES = (0.15, 0.2, 0.9)


def _amplitude(vehicle, mu: float, speed_mps: float) -> float:
    a_y = 1.2 * mu * G_MPS2
    c_f = vehicle.tire_front.cornering_stiffness_per_load_per_rad
    c_r = vehicle.tire_rear.cornering_stiffness_per_load_per_rad
    return vehicle.wheelbase_m * a_y / speed_mps**2 + (1.0 / c_f - 1.0 / c_r) * a_y / G_MPS2


def _scenario(kind: str, vehicle, tire, mu: float, seed: int) -> Scenario:
    speed = 15.0 if mu < 0.5 else 20.0
    amplitude = _amplitude(vehicle, mu, speed)
    if kind == "ramp":
        steer = SteerInput(CALM_S, CALM_S + STEER_S, amplitude, 1.0 / (4.0 * 10.0), 0.0)
    else:
        steer = SteerInput(CALM_S, CALM_S + STEER_S, amplitude, 0.25, 0.0)
    duration = CALM_S + STEER_S
    return Scenario(
        run_id=f"{kind}-{vehicle.name}-{tire.name}-{mu}",
        path=Path.straight(speed * duration + 100.0),
        mu=MuProfile.uniform(mu),
        speed=SpeedProfile([0.0, duration], [speed, speed]),
        vehicle=vehicle,
        tire=tire,
        steer=steer,
        duration_s=duration,
        seed=seed,
        effects=ProductionEffects.production(),
    )


def s_curves(radius_m: float, arc_m: float, n: int, step_m: float = 2.0) -> Path:
    """A 50 m straight, then n arcs of `radius_m` and `arc_m` each, turning left and right in turn."""
    x, y, heading = [0.0, 50.0], [0.0, 0.0], 0.0
    for k in range(n):
        side = 1.0 if k % 2 == 0 else -1.0
        for _ in range(round(arc_m / step_m)):
            heading += side * step_m / radius_m
            x.append(x[-1] + step_m * math.cos(heading))
            y.append(y[-1] + step_m * math.sin(heading))
    return Path(np.column_stack([x, y]))


def calm_drive(scenario: Scenario) -> Scenario:
    """80 s of calm driving on gentle curves both ways by the scenario's car on its road, before it: the same seed, so
    the same sensors (mounting, biases, radii: the production effects' draws)."""
    return scenario.replace(
        run_id=f"calm-{scenario.run_id}",
        path=s_curves(350.0, 220.0, 5),
        speed=SpeedProfile([0.0, 80.0], [11.0, 11.0]),
        steer=None,
        duration_s=80.0,
    )


def scenarios(split: str) -> list[Scenario]:
    vehicles, tires, seed = SPLITS[split]
    out = []
    for kind in ("ramp", "sine"):
        for vehicle in vehicles:
            for tire in tires:
                for mu in SURFACES:
                    out.append(_scenario(kind, vehicle, tire, mu, seed))
                    seed += 1
    return out


def run_rows(table: pa.Table, run_id: str, calibrated: bool) -> tuple[pa.Table, pa.Table, np.ndarray]:
    """A run's rows in a simulated table; the rows to estimate (its calm drive first where `calibrated`) and their
    segments (the calm drive 0, the run 1: the grid restarts, the calibration carries on)."""
    run = table.filter(pc.equal(table["run_id"], run_id))
    rows = pa.concat_tables([table.filter(pc.equal(table["run_id"], f"calm-{run_id}")), run]) if calibrated else run
    return run, rows, np.repeat([0, 1], [rows.num_rows - run.num_rows, run.num_rows])


@functools.cache
def estimated(split: str, calibrated: bool = True) -> dict[str, dict[str, np.ndarray]]:
    """Per run: the truth (mu, lateral utilisation, time) and pmf's estimates, after the calm drive (a segment of its
    own: the grid restarts, the calibration carries on) where `calibrated`."""
    runs = scenarios(split)
    table = simulate(runs + [calm_drive(s) for s in runs] if calibrated else runs)
    estimator = PMFEstimator()
    out = {}
    for scenario in runs:
        run, rows, segments = run_rows(table, scenario.run_id, calibrated)
        est = estimator.estimate_batch(rows, segments, scenario.vehicle).slice(rows.num_rows - run.num_rows)
        mu_true = run["mu"].to_numpy()
        ax, ay = run["ax_true_mps2"].to_numpy(), run["ay_true_mps2"].to_numpy()
        out[scenario.run_id] = {
            "t": np.arange(run.num_rows) * 0.1,
            "mu_true": mu_true,
            "u_true": np.hypot(ax, ay) / (mu_true * G_MPS2),
            "u_lat": np.abs(ay) / (mu_true * G_MPS2),
            "esc": run["esc_active"].to_numpy(zero_copy_only=False),
            "mu": est["mu"].to_numpy(),
            "lower": est["mu_lower"].to_numpy(),
            "upper": est["mu_upper"].to_numpy(),
        }
    return out


def pooled(split: str, ice: bool, low: float, high: float, calibrated: bool = True) -> dict[str, np.ndarray]:
    """The samples of the ice (or dry) runs whose true utilisation lies in [low, high)."""
    parts = [
        {k: v[(r["u_true"] >= low) & (r["u_true"] < high)] for k, v in r.items()}
        for r in estimated(split, calibrated).values()
        if (r["mu_true"][0] < 0.5) == ice
    ]
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def summary(split: str, calibrated: bool = True) -> str:
    """RMSE, coverage and mu_upper below 0.45 by true utilisation bin, on ice and dry (for the docs)."""
    lines = ["| surface | bin | n | RMSE | coverage | mu_upper < 0.45 |", "|---|---|---|---|---|---|"]
    for ice in (True, False):
        for name, low, high in (("< 0.5", 0.0, 0.5), ("0.5-0.8", 0.5, 0.8), (">= 0.8", 0.8, math.inf)):
            p = pooled(split, ice, low, high, calibrated)
            if p["mu"].size == 0:
                continue
            rmse = float(np.sqrt(np.mean((p["mu"] - p["mu_true"]) ** 2)))
            cover = float(((p["lower"] <= p["mu_true"]) & (p["mu_true"] <= p["upper"])).mean())
            low_upper = float((p["upper"] < 0.45).mean())
            lines.append(
                f"| {'ice' if ice else 'dry'} | {name} | {p['mu'].size} | {rmse:.3f} | {cover:.2f} | {low_upper:.2f} |"
            )
    return "\n".join(lines)
