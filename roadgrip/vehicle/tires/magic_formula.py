"""Combined-slip Magic Formula with friction scaling.

The combined slip is handled by the similarity method (Pacejka, Tire and Vehicle Dynamics, 3rd ed., 4.3.2): the linear
force demand of the two slips, F_lin = (C_x sigma, C_y tan alpha) / (1 + sigma) as in Dugoff's model, is passed through one
Magic Formula on its magnitude and the resulting force keeps the demand's direction:

    x = |F_lin| / (C D),  |F| = D sin(C atan(x - E (x - atan x))),  D = mu F_z.

The normalisation x = |F_lin| / (C D) (that is, B = 1 / (C D) per newton of demand) keeps the slip stiffnesses C_x and C_y at
zero slip whatever the road: friction scales the peak (D = mu F_z, the lambda_mu scaling of MF 5.2), not the stiffness, as on
real tires. Then |F| <= mu F_z always, and a sliding tire keeps sin(C pi / 2) of the peak (0.81 for C = 1.4).
"""

from dataclasses import dataclass, field
from math import atan, sin, sqrt, tan

from numba import njit

from roadgrip.validation import bounded, check_bounds
from roadgrip.vehicle.tires.base import STIFFNESS_SCALE_BOUNDS, TP_CX, TP_CY, TP_SHAPE, TireModel, clamp_slip_angle

MAGIC_FORMULA_ID = 1


@njit(cache=True)
def magic_formula_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu):
    shape_c = tp[TP_SHAPE]
    curvature_e = tp[TP_SHAPE + 1]
    peak_n = mu * fz_n  # D
    q = max(1.0 + slip_ratio, 1e-9)
    fx_lin = tp[TP_CX] * fz_n * slip_ratio / q
    fy_lin = tp[TP_CY] * fz_n * tan(clamp_slip_angle(slip_angle_rad)) / q
    demand = sqrt(fx_lin * fx_lin + fy_lin * fy_lin)
    if demand == 0.0 or peak_n <= 0.0:
        return 0.0, 0.0
    x = demand / (shape_c * peak_n)
    magnitude = peak_n * sin(shape_c * atan(x - curvature_e * (x - atan(x))))
    return fx_lin * magnitude / demand, fy_lin * magnitude / demand


@dataclass(frozen=True)
class MagicFormulaTire(TireModel):
    """Magic Formula on the combined slip. C in (1, 2) keeps one peak and sets the sliding-to-peak ratio sin(C pi / 2);
    E <= 1 keeps the curve rising up to its peak. `stiffness_scale` multiplies C_x and C_y (TireModel): through B = 1 / (C D)
    per newton of linear demand, the slope at zero slip scales and the peak stays D = mu F_z."""

    shape_c: float = field(default=1.4, metadata=bounded(1.0, 2.0, low_open=True))
    curvature_e: float = field(default=0.0, metadata=bounded(-10.0, 1.0))
    stiffness_scale: float = field(default=1.0, metadata=bounded(*STIFFNESS_SCALE_BOUNDS))

    name = "magic-formula"
    kernel_id = MAGIC_FORMULA_ID

    @property
    def kernel(self):
        return magic_formula_forces

    def __post_init__(self):
        check_bounds(self)

    def shape_params(self):
        return [self.shape_c, self.curvature_e]
