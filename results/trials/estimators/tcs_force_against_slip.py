"""Whether a 2WD car's own wheels can tell a stiff tire past its peak from a soft tire still below it while traction
control acts (docs/RESULTS.md, "Traction control past the tire's peak" and "Traction control's slip cycles"): over the
traction-control samples, the driven axle's force per load (m a_x over its load, catalogue profile) against its slip
(driven over undriven wheel speed), fitted by a line. Past the peak the force no longer rises with the controller's
slip cycles (slope near 0); below it the slope is the surface's stiffness. Physics validation split, a fresh car, every
production effect on.

    python results/trials/estimators/tcs_force_against_slip.py           # front-driven starts, the whole start
    python results/trials/estimators/tcs_force_against_slip.py chunks    # every 2WD run, one-second chunks

`chunks` fits the line over each second of traction control (the slip under 0.15, the car accelerating) where the slip's
spread is at least twice its noise (pmf's SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v; the fitted slope is divided by the
reliability 1 - noise / spread to undo the noise's attenuation), and prints each chunk's slope +- its standard error
and, in brackets, its ratio to the brush model's local slope C (1 - f / mu)^(2/3) at the run's true mu and stiffness
("sat" where the mean force reaches mu); then the wet and dry chunks' ratios.
"""

import collections
import sys

import numpy as np

from roadgrip.estimators.pmf import LOCK_SLIP, SLIP_MIN_SPEED_MPS, SLIP_SIGMA0, SLIP_SIGMA_PER_MPS
from roadgrip.evaluation.physics_benchmark import simulate_split
from roadgrip.units import G_MPS2

CHUNK_SAMPLES = 10  # one second at the split's 10 Hz
MIN_RELIABILITY = 0.75


def _driven_axle(run, scenario, profile):
    """The driven axle's slip over the undriven one and its force per load (catalogue profile)."""
    front = 0.5 * (run["wheel_speed_fl_radps"] + run["wheel_speed_fr_radps"])
    rear = 0.5 * (run["wheel_speed_rl_radps"] + run["wheel_speed_rr_radps"])
    fwd = scenario.vehicle.drive == "fwd"
    driven, undriven = (front, rear) if fwd else (rear, front)
    ax = run["accel_lon_mps2"]
    lf = profile.cg_to_front_axle_m
    lr = profile.wheelbase_m - lf
    h = profile.cg_height_m
    fz = profile.mass_kg * (G_MPS2 * (lr if fwd else lf) + (-ax if fwd else ax) * h) / profile.wheelbase_m
    return driven / np.maximum(undriven, 1e-3) - 1.0, profile.mass_kg * ax / fz, undriven * profile.wheel_radius_m


def chunks(split, table) -> None:
    ratios = collections.defaultdict(list)
    readable = collections.Counter()
    for scenario, _ in split.drawn:
        if scenario.vehicle.drive == "awd":
            continue
        rows = table["run_id"] == scenario.run_id
        run = {c: values[rows] for c, values in table.items()}
        profile = split.profiles[scenario.run_id]
        slip, force, v = _driven_axle(run, scenario, profile)
        acting = run["tcs_active"].astype(bool) & (v >= SLIP_MIN_SPEED_MPS) & (np.abs(slip) < LOCK_SLIP)
        acting &= run["accel_lon_mps2"] > 0.0
        idx = np.flatnonzero(acting)
        if idx.size < CHUNK_SAMPLES:
            continue
        mu = run["mu"][0]
        c = profile.tire_front.longitudinal_stiffness_per_load * scenario.tire.stiffness_scale
        cells = []
        for k in range(0, idx.size - CHUNK_SAMPLES + 1, CHUNK_SAMPLES):
            rows_k = idx[k : k + CHUNK_SAMPLES]
            if rows_k[-1] - rows_k[0] != CHUNK_SAMPLES - 1:
                continue
            s, f = slip[rows_k], force[rows_k]
            noise = np.mean((SLIP_SIGMA0 + SLIP_SIGMA_PER_MPS / v[rows_k]) ** 2)
            reliability = 1.0 - noise / s.var() if s.var() > 0.0 else 0.0
            if reliability < MIN_RELIABILITY:
                cells.append("-")
                continue
            fit, offset = np.polyfit(s, f, 1)
            se = (
                np.std(f - fit * s - offset)
                * np.sqrt(CHUNK_SAMPLES / (CHUNK_SAMPLES - 2))
                / np.sqrt(CHUNK_SAMPLES * s.var())
            )
            slope = fit / reliability
            brush = c * max(1.0 - f.mean() / mu, 0.0) ** (2.0 / 3.0)
            readable[scenario.condition] += 1
            if brush > 1.0:
                ratios[scenario.condition].append(slope / brush)
            cells.append(
                f"{slope:.1f}+-{se / reliability:.1f}" + (f"({slope / brush:.2f})" if brush > 1.0 else "(sat)")
            )
        print(
            f"{scenario.run_id}: {scenario.manoeuvre} {scenario.vehicle.drive} {scenario.condition} {mu:.2f}, C {c:.1f}, "
            f"force {force[acting].mean():.2f}: {' '.join(cells)}"
        )
    print(f"readable chunks by surface: {dict(readable)}")
    for surface in ("wet", "dry"):
        print(f"{surface}: measured / brush slope {np.round(sorted(ratios[surface]), 2).tolist()}")


def starts(split, table) -> None:
    print("run: surface mu, tire, stiffness | TCS samples, slip range, force range, slope (per unit slip) against C")
    for scenario, _ in split.drawn:
        if scenario.manoeuvre != "acceleration" or scenario.vehicle.drive != "fwd":
            continue
        rows = table["run_id"] == scenario.run_id
        run = {c: values[rows] for c, values in table.items()}
        profile = split.profiles[scenario.run_id]
        slip, force, v = _driven_axle(run, scenario, profile)
        tcs = run["tcs_active"].astype(bool) & (v > 5.0)
        calm = ~tcs & (np.abs(run["accel_lon_mps2"]) < 0.5) & (v > profile.wheel_radius_m)
        if tcs.sum() < 20 or calm.sum() < 5:
            continue
        slip = slip - np.median(slip[calm])
        s, f = slip[tcs], force[tcs]
        slope = np.polyfit(s, f, 1)[0]
        c = profile.tire_front.longitudinal_stiffness_per_load * scenario.tire.stiffness_scale
        print(
            f"{scenario.run_id}: {scenario.condition} {run['mu'][0]:.2f}, {type(scenario.tire).__name__}, "
            f"{scenario.tire.stiffness_scale:.2f} | {tcs.sum()}, slip {np.percentile(s, 10):.3f}-{np.percentile(s, 90):.3f}, "
            f"force {np.percentile(f, 10):.2f}-{np.percentile(f, 90):.2f}, slope {slope:.1f} against C {c:.1f}"
        )


def main(mode: str = "starts") -> None:
    split = simulate_split("validation")
    runs, _ = split.tables[None]
    columns = ("run_id", "mu", "tcs_active", "accel_lon_mps2") + tuple(
        f"wheel_speed_{w}_radps" for w in ("fl", "fr", "rl", "rr")
    )
    table = {c: runs[c].to_numpy(zero_copy_only=False) for c in columns}
    {"starts": starts, "chunks": chunks}[mode](split, table)


if __name__ == "__main__":
    main(*sys.argv[1:2])
