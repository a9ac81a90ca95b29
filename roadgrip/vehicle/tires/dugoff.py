"""Dugoff tire model (paper eq. 3-5 and 7; Dugoff, Fancher and Segel, 1970).

The paper's print of the model has two slips that we correct, because as printed the force exceeds mu F_z:
- eq. 7 lacks the factor 2 of Dugoff's original, lambda = mu F_z (1 + sigma) / (2 sqrt((C_x sigma)^2 + (C_y tan alpha)^2));
- eq. 5 has its two cases swapped: f = 1 in the linear region (lambda >= 1), f = (2 - lambda) lambda when saturated.
With both, |F| = mu F_z (2 - lambda) / 2 <= mu F_z in the saturated region, and |F| -> mu F_z as the slip grows.
"""

from dataclasses import dataclass, field
from math import sqrt, tan

from numba import njit

from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.tires.base import STIFFNESS_SCALE_BOUNDS, TP_CX, TP_CY, TireModel, clamp_slip_angle

DUGOFF_ID = 0


@njit(cache=True)
def dugoff_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu):
    cx = tp[TP_CX] * fz_n
    cy = tp[TP_CY] * fz_n
    q = max(1.0 + slip_ratio, 1e-9)  # 1 + sigma, eq. 3-4; zero only at a locked wheel
    fx_lin = cx * slip_ratio  # C_x sigma
    fy_lin = cy * tan(clamp_slip_angle(slip_angle_rad))  # C_y tan(alpha)
    demand = sqrt(fx_lin * fx_lin + fy_lin * fy_lin)
    if demand == 0.0 or fz_n <= 0.0:
        return 0.0, 0.0
    lam = mu * fz_n * q / (2.0 * demand)  # eq. 7 (Dugoff's original, with the 2)
    if lam >= 1.0:
        return fx_lin / q, fy_lin / q  # eq. 3-4 with f = 1
    k = mu * fz_n * (2.0 - lam) / (2.0 * demand)  # f(lambda) / (1 + sigma) with f = (2 - lambda) lambda, eq. 5
    return fx_lin * k, fy_lin * k


@dataclass(frozen=True)
class DugoffTire(TireModel):
    """Dugoff's model: linear up to the friction circle, then a smooth saturation towards mu F_z. `stiffness_scale`
    multiplies C_x and C_y (TireModel)."""

    stiffness_scale: float = field(default=1.0, metadata=bounded(*STIFFNESS_SCALE_BOUNDS))

    name = "dugoff"
    kernel_id = DUGOFF_ID

    @property
    def kernel(self):
        return dugoff_forces

    def __post_init__(self):
        check_bounds(self)

    def shape_params(self):
        return []
