"""Unit conversions, in one place. Everything else in roadgrip is SI with angles in radians."""

import math

G_MPS2 = 9.80665  # standard gravity (ISO 80000-3)
KMH_PER_MPS = 3.6
INCH_M = 0.0254


def kmh_to_mps(speed_kmh):
    return speed_kmh / KMH_PER_MPS


def mps_to_kmh(speed_mps):
    return speed_mps * KMH_PER_MPS


def deg_to_rad(angle_deg):
    return angle_deg * (math.pi / 180.0)


def rad_to_deg(angle_rad):
    return angle_rad * (180.0 / math.pi)
