"""The cost of one Phi as pmf reads it (lateral.normal_cdf: a table of scipy's ndtr read linearly) against erf's, and
how many Phi ABS's likelihood reads in one sample (docs/ESTIMATORS.md, "pmf's normal distribution function").

    python results/trials/estimators/normal_cdf_speed.py
"""

import time
from math import erf, sqrt

import numpy as np
from numba import njit

from roadgrip.bench.estimate import BENCH_RUN
from roadgrip.estimators import pmf
from roadgrip.estimators.lateral import normal_cdf
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


@njit
def _erf_cdf(x):
    return 0.5 * (1.0 + erf(x / sqrt(2.0)))


@njit
def _sum(cdf, n):
    acc = 0.0
    for r in range(n):
        acc += cdf(-5.0 + (r % 10000) * 0.001)
    return acc


@njit
def _abs_calls(u_car, s_car, u_first, s_first, c0):
    """The Phi _abs_likelihood evaluates (_soft_between's ends within 6 sigma) at these utilisations."""
    step = (pmf.ABS_SLIP_BAND[1] - pmf.ABS_SLIP_BAND[0]) / pmf.ABS_BAND_POINTS
    calls = 0
    for i in range(pmf.NM):
        mu = pmf.MU_GRID[i]
        s_lo = sqrt(s_car * s_car + (0.03 * mu) ** 2)
        s_hi = sqrt(s_first * s_first + (0.03 * mu) ** 2)
        for j in range(pmf.NC):
            c = c0 * pmf.C_FACTORS[j]
            for k in range(pmf.ABS_BAND_POINTS):
                slip = pmf.ABS_SLIP_BAND[0] + (k + 0.5) * step
                p = mu if c * slip >= 3.0 * mu else pmf._brush_force(slip, mu, c)
                a, b = (p - u_car) / s_lo, (u_first - p) / s_hi
                if a >= -6.0 and b >= -6.0:
                    calls += (a <= 6.0) + (b <= 6.0)
                if c * slip >= 3.0 * mu:
                    break
    return calls


def main() -> None:
    n = 10_000_000
    for name, cdf in (("erf", _erf_cdf), ("table", normal_cdf)):
        _sum(cdf, 10)
        t0 = time.perf_counter()
        _sum(cdf, n)
        print(f"{name}: {(time.perf_counter() - t0) / n * 1e9:.1f} ns a Phi")
    table = simulate([next(s for s in paper_scenarios() if s.run_id == BENCH_RUN)])
    print(f"{BENCH_RUN}: ABS on {np.mean(table['abs_active'].to_numpy()):.3f} of the samples")
    c0 = pmf.pack(PAPER_SUV)[pmf.Q_C0]
    for u_car, u_first in ((0.2, 0.25), (0.5, 0.55), (0.8, 0.9)):
        print(f"ABS at u_car {u_car}, u_first {u_first}: {_abs_calls(u_car, 0.02, u_first, 0.03, c0)} Phi a sample")


if __name__ == "__main__":
    main()
