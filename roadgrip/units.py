"""Unit conversions, in one place. Everything else in roadgrip is SI with angles in radians.

A factor `X_PER_Y` is the value in X of one Y: multiply a value in Y by it to get X; divide a value in X by it to get
Y."""

import math

G_MPS2 = 9.80665  # standard gravity (ISO 80000-3)
KMH_PER_MPS = 3.6  # 3600 s per hour / 1000 m per km
MPS_PER_MPH = 0.44704  # the international mile, 1609.344 m, per 3600 s (exact)
MPH_PER_MPS = 1.0 / MPS_PER_MPH
RPM_PER_RADPS = 60.0 / (2.0 * math.pi)  # 60 s per minute / 2 pi rad per revolution
DEG_PER_RAD = 180.0 / math.pi  # also deg/s per rad/s
INCH_M = 0.0254  # the international inch (exact)


def kmh_to_mps(speed_kmh):
    return speed_kmh / KMH_PER_MPS


def mps_to_kmh(speed_mps):
    return speed_mps * KMH_PER_MPS


def deg_to_rad(angle_deg):
    return angle_deg * (math.pi / 180.0)


def rad_to_deg(angle_rad):
    return angle_rad * DEG_PER_RAD
