"""How many runs of the random preset reach the limit: body sideslip beyond 10 degrees, by manoeuvre; and any NaN.

Run: python results/trials/simulator/random_preset_limits.py [runs] [seed]   (default 500 runs, seed 0; quoted in docs/SIMULATOR.md)
"""

import collections
import sys

import numpy as np

from roadgrip.sim.integrator import CHANNELS
from roadgrip.sim.presets import random_scenarios
from roadgrip.sim.simulate import simulate_truth

CH = {name: k for k, name in enumerate(CHANNELS)}


def main(runs: int = 500, seed: int = 0):
    scenarios = random_scenarios(runs, seed)
    outs = simulate_truth(scenarios)
    sliding = collections.Counter()
    for scenario, out in zip(scenarios, outs):
        sideslip = np.arctan2(out[:, CH["vy_mps"]], np.maximum(np.abs(out[:, CH["vx_mps"]]), 1.0))
        if np.abs(sideslip).max() > np.radians(10.0):
            sliding[scenario.manoeuvre] += 1
    print(f"{sum(sliding.values())} of {runs} runs exceed 10 deg of sideslip: {dict(sliding)}")
    print(f"runs with a NaN or inf: {sum(not np.isfinite(out).all() for out in outs)}")


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
