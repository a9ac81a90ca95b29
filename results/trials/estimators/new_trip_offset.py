"""The fleet benchmark's false ice warning traced (issue 23; docs/RESULTS.md, "A new trip's gyro bias").

    PYTHONPATH=. python results/trials/estimators/new_trip_offset.py

Replays vehicle bench-028 of report seed 0 (every trip up to the on-ramp trip at 1652.6 s) through pmf's kernel and
prints, per trip, the understeer angle's true offset (delta - L r / v from the sensors minus the simulator's true
alpha_f - alpha_r, the steering angle's and gyro's biases through the kinematics) against the offset the understeer
line carries at the trip's end, its slope and the slope's sigma; then, each second from the patch on, the true mu, the
estimate and the line's state. The slip line (s0, 1 / C) is printed too: it is the car's (the front/rear slip it takes
out is the true slip's, to 0.001), not the fault.
"""

from __future__ import annotations

import numpy as np

from roadgrip.estimators import pmf as P
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario
from roadgrip.sim.simulate import simulate

VEHICLE, BEFORE_S, FROM_S, TO_S = "bench-028", 1653.0, 1674.0, 1712.0

scenario = make_scenario(0, FleetConfig())
trips = [t for t in scenario.trips if t.vehicle_id == VEHICLE and t.depart_s <= BEFORE_S]
table = simulate([t.scenario for t in trips], start_epoch_ms=0)
depart = {t.scenario.run_id: t.depart_s for t in trips}
run_ids = table["run_id"].to_numpy(zero_copy_only=False)
t_s = np.array([depart[r] for r in run_ids]) + table["t_s"].to_numpy()
order = np.argsort(t_s, kind="stable")
t_s, run_ids = np.round(t_s[order], 1), run_ids[order]


def col(name):
    return table[name].to_numpy(zero_copy_only=False)[order]


samples = np.full((t_s.size, P.N_S), np.nan)
for k, name in enumerate(P.SAMPLE_COLUMNS[: P.N_BASE]):
    samples[:, k] = col(name).astype(float)
samples[:, P.S_T] = np.round(t_s * 1000.0)
vehicle = scenario.kinds[VEHICLE]
q = P.pack(vehicle)
mem = np.zeros(P.N_MEM)
P.init_memory(mem, q)
out = np.zeros(P.N_OUT)
wheelbase = vehicle.wheelbase_m
v = col("vx_true_mps")
measured = samples[:, P.S_SWA] / vehicle.steering_ratio - wheelbase * samples[:, P.S_R] / np.maximum(v, 1.0)
angle = {w: col(f"slip_angle_{w}_rad") for w in ("fl", "fr", "rl", "rr")}
true_offset = measured - 0.5 * (angle["fl"] + angle["fr"] - angle["rl"] - angle["rr"])
mu_true = col("mu")
print("trip      depart_s  true offset (mrad)  line's offset  slope  slope sigma  s0       1/C")
t_prev = 0.0
for k in range(t_s.size):
    t_prev = P.pmf_step(mem, q, samples[k], t_prev, out)
    last = k + 1 == t_s.size or run_ids[k + 1] != run_ids[k]
    if last:
        fast = (run_ids == run_ids[k]) & (v > 5.0)
        print(
            f"{run_ids[k]}  {depart[run_ids[k]]:7.1f}  {1e3 * np.median(true_offset[fast]):+6.2f}"
            f"  {1e3 * mem[P.K_LAT_B]:+6.2f}  {mem[P.K_LAT_S]:.3f}  {np.sqrt(mem[P.K_LP11]):.3f}"
            f"  {mem[P.K_S0]:+.4f}  {mem[P.K_SLOPE]:.4f}"
        )
    if FROM_S <= t_s[k] <= TO_S and k % 10 == 0:
        print(
            f"  {t_s[k]:7.1f} s  mu {mu_true[k]:.2f}  estimate {out[P.O_MU]:.2f} [{out[P.O_LOWER]:.2f}, "
            f"{out[P.O_UPPER]:.2f}]  offset {1e3 * mem[P.K_LAT_B]:+.2f} mrad  slope {mem[P.K_LAT_S]:.3f}"
        )
