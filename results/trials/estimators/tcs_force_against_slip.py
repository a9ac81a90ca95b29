"""Whether a front-driven car's own wheels can tell a stiff tire past its peak from a soft tire still below it while
traction control acts (docs/RESULTS.md, "Traction control past the tire's peak"): over each start's traction-control
samples, the driven axle's force per load (m a_x over the front axle's load, catalogue profile) against its slip (front
over rear wheel speed, less the calm driving's ratio before the start), fitted by a line. Past the peak the force no
longer rises with the controller's slip cycles (slope near 0); below it the slope is the surface's stiffness. Physics
validation split, front-driven starts, a fresh car, every production effect on.

    python results/trials/estimators/tcs_force_against_slip.py
"""

import numpy as np

from roadgrip.evaluation.physics_benchmark import simulate_split
from roadgrip.units import G_MPS2


def main() -> None:
    split = simulate_split("validation")
    runs, _ = split.tables[None]
    columns = ("run_id", "mu", "tcs_active", "accel_lon_mps2") + tuple(
        f"wheel_speed_{w}_radps" for w in ("fl", "fr", "rl", "rr")
    )
    table = {c: runs[c].to_numpy(zero_copy_only=False) for c in columns}
    print("run: surface mu, tire, stiffness | TCS samples, slip range, force range, slope (per unit slip) against C")
    for scenario, _ in split.drawn:
        if scenario.manoeuvre != "acceleration" or scenario.vehicle.drive != "fwd":
            continue
        rows = table["run_id"] == scenario.run_id
        run = {c: values[rows] for c, values in table.items()}
        profile = split.profiles[scenario.run_id]
        front = 0.5 * (run["wheel_speed_fl_radps"] + run["wheel_speed_fr_radps"])
        rear = 0.5 * (run["wheel_speed_rl_radps"] + run["wheel_speed_rr_radps"])
        tcs = run["tcs_active"].astype(bool) & (rear * profile.wheel_radius_m > 5.0)
        calm = ~tcs & (np.abs(run["accel_lon_mps2"]) < 0.5) & (rear > 1.0)
        if tcs.sum() < 20 or calm.sum() < 5:
            continue
        slip = front / np.maximum(rear, 1e-3) - 1.0 - np.median(front[calm] / rear[calm] - 1.0)
        lr = profile.wheelbase_m - profile.cg_to_front_axle_m
        ax = run["accel_lon_mps2"]
        fz_front = profile.mass_kg * (G_MPS2 * lr - ax * profile.cg_height_m) / profile.wheelbase_m
        force = profile.mass_kg * ax / fz_front
        s, f = slip[tcs], force[tcs]
        slope = np.polyfit(s, f, 1)[0]
        c = profile.tire_front.longitudinal_stiffness_per_load * scenario.tire.stiffness_scale
        print(
            f"{scenario.run_id}: {scenario.condition} {run['mu'][0]:.2f}, {type(scenario.tire).__name__}, "
            f"{scenario.tire.stiffness_scale:.2f} | {tcs.sum()}, slip {np.percentile(s, 10):.3f}-{np.percentile(s, 90):.3f}, "
            f"force {np.percentile(f, 10):.2f}-{np.percentile(f, 90):.2f}, slope {slope:.1f} against C {c:.1f}"
        )


if __name__ == "__main__":
    main()
