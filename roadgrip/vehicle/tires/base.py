"""The one interface of the tire models.

A tire model maps the slips of one tire, its vertical load and the road's adhesion coefficient to the force the road puts on
the tire, in the wheel frame: fx along the wheel's heading, fy to its left. Sign conventions are the paper's: slip ratio as
eq. 6 (positive when driving, -1 at a locked wheel), slip angle as eq. 8 (positive alpha gives positive fy).

Each model is a numba kernel `forces(tp, slip_ratio, slip_angle_rad, fz_n, mu) -> (fx_n, fy_n)` over a packed parameter row
`tp` (so the simulator's compiled loop can call it) and a Python class that packs the row and evaluates arrays.
"""

from __future__ import annotations

import functools
from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np
from numba import njit

from roadgrip.vehicle.params import TireParams

# Layout of a packed tire row: [model id, C_x/F_z, C_y/F_z, model-specific parameters...]
TP_MODEL, TP_CX, TP_CY, TP_SHAPE = 0, 1, 2, 3
TP_LEN = 40
MAX_SLIP_ANGLE_RAD = 1.4  # tan() stays finite; a tire never runs beyond 80 degrees of slip in the simulator


STIFFNESS_SCALE_BOUNDS = (0.3, 3.0)  # a tire's slip stiffnesses times this factor: worn, under-inflated, winter tires


class TireModel(ABC):
    """A tire model: `forces` over arrays, `row` to pack it for the compiled simulator.

    Every model has a `stiffness_scale` (default 1): the longitudinal and cornering slip stiffnesses at zero slip are the
    vehicle's `TireParams` times it, while the peak stays mu F_z (wear, inflation and tire make move the initial slope
    by some +-30 % without changing the road's adhesion). Dugoff and the Magic Formula take it through C_x and C_y; the
    Burckhardt model through its slip axis (see burckhardt.py)."""

    name: str
    kernel_id: int
    stiffness_scale: float
    # whether the model's slope at zero slip changes with the road's surface (Burckhardt's table carries one per
    # surface); where it does not, a surface's own slope is the stiffness scale's to carry
    slope_by_surface: ClassVar[bool] = False

    @abstractmethod
    def shape_params(self) -> list[float]:
        """The model-specific parameters, in the order its kernel reads them from tp[TP_SHAPE:]."""

    def row(self, tire: TireParams) -> np.ndarray:
        tp = np.zeros(TP_LEN)
        tp[TP_MODEL] = self.kernel_id
        tp[TP_CX] = tire.longitudinal_stiffness_per_load * self.stiffness_scale
        tp[TP_CY] = tire.cornering_stiffness_per_load_per_rad * self.stiffness_scale
        shape = self.shape_params()
        tp[TP_SHAPE : TP_SHAPE + len(shape)] = shape
        return tp

    @property
    @abstractmethod
    def kernel(self):
        """The model's compiled scalar kernel `(tp, slip_ratio, slip_angle_rad, fz_n, mu) -> (fx_n, fy_n)`."""

    def forces(self, tire: TireParams, slip_ratio, slip_angle_rad, fz_n, mu):
        """(fx_n, fy_n) arrays for broadcastable inputs: slip ratio, slip angle [rad], vertical load [N], road mu."""
        forces_array = _array_loop(self.kernel)
        s, a, fz, m = (
            np.ascontiguousarray(x, dtype=np.float64) for x in np.broadcast_arrays(slip_ratio, slip_angle_rad, fz_n, mu)
        )
        fx = np.empty(s.size)
        fy = np.empty(s.size)
        forces_array(self.row(tire), s.ravel(), a.ravel(), fz.ravel(), m.ravel(), fx, fy)
        return fx.reshape(s.shape), fy.reshape(s.shape)


@functools.cache
def _array_loop(kernel):
    """A compiled loop of one model's scalar kernel over flat arrays (one per model, compiled on first use)."""

    @njit
    def forces_array(tp, slip_ratio, slip_angle_rad, fz_n, mu, fx_out, fy_out):
        for i in range(slip_ratio.size):
            fx_out[i], fy_out[i] = kernel(tp, slip_ratio[i], slip_angle_rad[i], fz_n[i], mu[i])

    return forces_array


@njit(cache=True)
def clamp_slip_angle(alpha_rad):
    return min(max(alpha_rad, -MAX_SLIP_ANGLE_RAD), MAX_SLIP_ANGLE_RAD)
