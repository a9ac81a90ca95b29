"""Dispatch from a packed tire row to its model's kernel, for the compiled simulator (TireModel.forces evaluates one
model over arrays without it)."""

from numba import njit

from roadgrip.vehicle.tires.base import TP_MODEL
from roadgrip.vehicle.tires.burckhardt import burckhardt_forces
from roadgrip.vehicle.tires.dugoff import DUGOFF_ID, dugoff_forces
from roadgrip.vehicle.tires.magic_formula import MAGIC_FORMULA_ID, magic_formula_forces


@njit(cache=True)
def tire_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu):
    model = int(tp[TP_MODEL])
    if model == DUGOFF_ID:
        return dugoff_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu)
    if model == MAGIC_FORMULA_ID:
        return magic_formula_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu)
    return burckhardt_forces(tp, slip_ratio, slip_angle_rad, fz_n, mu)
