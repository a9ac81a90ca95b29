"""Burckhardt tire-road model on tabulated surfaces, scaled to the road's adhesion coefficient.

mu(s) = c1 (1 - exp(-c2 s)) - c3 s on the resultant slip s (Burckhardt 1993; the surfaces of burckhardt_surfaces.csv). The
road's adhesion coefficient is the peak of its curve. For a road of adhesion mu the model takes the curve of the named surface,
or by default of the tabulated surface whose peak is nearest to mu (ice for 0.05, snow for 0.19, wet asphalt for 0.8, ...),
and scales it so that its peak is mu: the shape of the curve (where the peak lies, how much is lost when sliding) follows the
surface, the peak follows the road.

Combined slip: s_x = sigma (eq. 6), s_y = tan(alpha) C_y / C_x, so that the cornering stiffness keeps the tire's ratio to the
longitudinal one; s = |(s_x, s_y)| and the force points along (s_x, s_y).

Stiffness: the curve is read at k s (k = `stiffness_scale`, capped at the table's range, 1), so the slope at zero slip is
k mu / peak c1 c2 F_z and the peak, still mu F_z, moves to s* / k: a stiffer tire reaches the same adhesion at a smaller
slip. The curve's own slope at zero slip does not depend on C_x, whose ratio to C_y only shapes the combined slip.
"""

import csv
from dataclasses import dataclass, field
from importlib import resources
from math import exp, log, sqrt, tan
from typing import ClassVar

from numba import njit

from roadgrip.validation import bounded, check_bounds, check_choice
from roadgrip.vehicle.tires.base import STIFFNESS_SCALE_BOUNDS, TP_CX, TP_CY, TP_SHAPE, TireModel, clamp_slip_angle

BURCKHARDT_ID = 2
_PER_SURFACE = 4  # c1, c2, c3, peak


def load_surfaces() -> dict[str, tuple[float, float, float]]:
    """{surface: (c1, c2, c3)} from the packaged table."""
    text = resources.files("roadgrip.vehicle.tires").joinpath("burckhardt_surfaces.csv").read_text()
    rows = csv.DictReader(line for line in text.splitlines() if not line.startswith("#"))
    return {r["surface"]: (float(r["c1"]), float(r["c2"]), float(r["c3"])) for r in rows}


SURFACES = load_surfaces()


def burckhardt_curve(c1, c2, c3, slip):
    """mu(s) of one surface, for s in [0, 1]."""
    return c1 * (1.0 - exp(-c2 * slip)) - c3 * slip


def peak_slip(c1, c2, c3) -> float:
    """Slip of the curve's maximum: d mu / ds = c1 c2 exp(-c2 s) - c3 = 0, capped to [0, 1]."""
    if c3 <= 0.0:
        return 1.0
    return min(max(log(c1 * c2 / c3) / c2, 0.0), 1.0)


def peak_mu(c1, c2, c3) -> float:
    return burckhardt_curve(c1, c2, c3, peak_slip(c1, c2, c3))


@njit(cache=True)
def burckhardt_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu):
    n_surfaces = int(tp[TP_SHAPE])
    best = 0
    for k in range(1, n_surfaces):
        base = TP_SHAPE + 1 + _PER_SURFACE * k
        if abs(tp[base + 3] - mu) < abs(tp[TP_SHAPE + 1 + _PER_SURFACE * best + 3] - mu):
            best = k
    base = TP_SHAPE + 1 + _PER_SURFACE * best
    c1, c2, c3, surface_peak = tp[base], tp[base + 1], tp[base + 2], tp[base + 3]
    stiffness_scale = tp[TP_SHAPE + 1 + _PER_SURFACE * n_surfaces]
    s_x = slip_ratio
    s_y = tan(clamp_slip_angle(slip_angle_rad)) * tp[TP_CY] / tp[TP_CX]
    s = sqrt(s_x * s_x + s_y * s_y)
    if s == 0.0 or fz_n <= 0.0 or mu <= 0.0:
        return 0.0, 0.0
    s_eff = min(stiffness_scale * s, 1.0)
    mu_used = max(mu / surface_peak * (c1 * (1.0 - exp(-c2 * s_eff)) - c3 * s_eff), 0.0)
    force = mu_used * fz_n
    return force * s_x / s, force * s_y / s


@dataclass(frozen=True)
class BurckhardtTire(TireModel):
    """Burckhardt curves; `surface` fixes the curve's shape, None picks the surface whose peak is nearest the road's mu;
    `stiffness_scale` stretches the slip axis (module docstring)."""

    surface: str | None = None
    stiffness_scale: float = field(default=1.0, metadata=bounded(*STIFFNESS_SCALE_BOUNDS))
    slope_by_surface: ClassVar[bool] = True

    name = "burckhardt"
    kernel_id = BURCKHARDT_ID

    @property
    def kernel(self):
        return burckhardt_forces

    def __post_init__(self):
        check_bounds(self)
        if self.surface is not None:
            check_choice("BurckhardtTire", "surface", self.surface, set(SURFACES))

    def shape_params(self):
        names = [self.surface] if self.surface else list(SURFACES)
        params = [float(len(names))]
        for name in names:
            c1, c2, c3 = SURFACES[name]
            params += [c1, c2, c3, peak_mu(c1, c2, c3)]
        return params + [self.stiffness_scale]
