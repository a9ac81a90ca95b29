"""A simulated single-wheel sideway-force test vehicle (SCRIM-like): the reference instrument of the paper's Table 7.

The machine tows (or carries) a test wheel that rolls freely but is yawed at a fixed slip angle to the direction of
travel, on a road wetted ahead of the wheel; it measures the force perpendicular to the wheel's plane and reports the
sideway force coefficient SFC = F_y / F_z, averaged over 10 m lengths. Standard settings (BS 7941-1:2006, SCRIM; CEN/TS
15901-6):

| setting              | value              | here                                                   |
|----------------------|--------------------|--------------------------------------------------------|
| slip angle           | 20 degrees         | SidewayForceWheel.slip_angle_rad                       |
| test speed           | 50 km/h            | speed_mps: with the sample period, the sample spacing  |
| static vertical load | 200 kg, about 2 kN | load_n (F_y is computed in N; Burckhardt's force is proportional to the load, so SFC does not depend on it) |
| water film           | 0.5 mm nominal     | the wet surface's curve (Burckhardt "wet_asphalt"): no film-depth model |
| report length        | 10 m               | report_length_m                                        |

Physics (Burckhardt's model on the package's tabulated surfaces, roadgrip/vehicle/tires/burckhardt.py). A free-rolling
wheel at slip angle alpha turns at the circumferential speed v cos(alpha), the component of the travel speed v in its
plane, so its contact patch slides at v sin(alpha), perpendicular to the plane. Burckhardt's slips are sliding speed over
travel speed (Kiencke & Nielsen, Automotive Control Systems, 2nd ed., 7.1): s_x = 0, s_y = sin(alpha), resultant
s = sin(alpha) (0.342 at 20 degrees). The friction force acts against the sliding, i.e. along the wheel's axis:

    F_y = mu(s) F_z,   mu(s) = (mu_road / mu_peak) (c1 (1 - exp(-c2 s)) - c3 s),   SFC = F_y / F_z = mu(sin alpha)

with (c1, c2, c3) of the wet surface and mu_peak the peak of its curve: the road's adhesion coefficient mu_road (the
curve's peak, as everywhere in roadgrip) scales the curve, exactly as BurckhardtTire does. The peak of wet asphalt lies at
s = 0.13; at s = 0.34 the tire is well past it, so the SFC is below the road's peak mu (0.738 against 0.801 on the
tabulated wet asphalt).

Why Burckhardt and not the Magic Formula: the paper's expected ratio (0.68) is Burckhardt's; its falling branch past the
peak (c3) is measured for each surface, wet asphalt included, while the Magic Formula's sliding level sin(C pi / 2) is one
shape factor with no wet-road value; and it gives the SFC in closed form. Why not the simulator's Burckhardt kernel as it
stands: the kernel's lateral slip is tan(alpha) C_y / C_x, chosen to keep a car tire's cornering stiffness; a test
wheel at 20 degrees slides, and its friction follows the sliding speed (the tests check that the kernel agrees when its
stiffness ratio makes tan(alpha) C_y / C_x = sin(alpha)).

Measurement scatter (assumptions, documented in docs/RESULTS.md): a per-run relative bias of 2.5 % (1 sigma, shared by
both wheels: test-wheel temperature, water flow, the line driven), the spread of the paper's own four SFC runs (0.408-0.431, sd 0.011 = 2.5 % of
their mean); and 0.01 of SFC (1 sigma) of noise on each 10 m value.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from roadgrip.sim.roads import MuProfile
from roadgrip.units import G_MPS2, deg_to_rad, kmh_to_mps
from roadgrip.validation import bounded, check_bounds, check_choice
from roadgrip.vehicle.tires.burckhardt import SURFACES, peak_mu

SCRIM_SLIP_ANGLE_RAD = deg_to_rad(20.0)  # BS 7941-1: test wheel at 20 degrees to the direction of travel
SCRIM_SPEED_MPS = kmh_to_mps(50.0)  # BS 7941-1 standard test speed
SCRIM_LOAD_N = 200.0 * G_MPS2  # BS 7941-1: static vertical load of 200 kg on the test wheel
SCRIM_REPORT_LENGTH_M = 10.0  # BS 7941-1: SFC reported as the mean of each 10 m length
SFC_RUN_BIAS_SHARE = 0.025  # sd of the paper's four SFC means over their mean (Table 7): 0.0107 / 0.424
SFC_REPORT_NOISE = 0.01  # assumed scatter of one 10 m value, in units of SFC
TRACKS = ("left", "right")  # the paper's test vehicle has two test wheels, one in each wheel track


def free_rolling_slip(slip_angle_rad) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Burckhardt's (s_x, s_y, resultant s) of a free-rolling wheel at a slip angle: (0, sin alpha, sin alpha)."""
    s_y = np.abs(np.sin(np.asarray(slip_angle_rad, dtype=np.float64)))
    return np.zeros_like(s_y), s_y, s_y


def burckhardt_sfc(mu_road, slip_angle_rad: float = SCRIM_SLIP_ANGLE_RAD, surface: str = "wet_asphalt") -> np.ndarray:
    """SFC = mu(sin alpha) of a free-rolling wheel on a road of adhesion coefficient mu_road (the peak of its curve), the
    curve's shape from `surface`."""
    check_choice("burckhardt_sfc", "surface", surface, set(SURFACES))
    c1, c2, c3 = SURFACES[surface]
    _, _, s = free_rolling_slip(slip_angle_rad)
    s = np.minimum(s, 1.0)  # the table's range of slip
    curve = c1 * (1.0 - np.exp(-c2 * s)) - c3 * s  # Burckhardt's mu(s)
    return np.maximum(np.asarray(mu_road, dtype=np.float64) / peak_mu(c1, c2, c3) * curve, 0.0)


@dataclass(frozen=True)
class SfcSurvey:
    """One run of the test vehicle along a road: 10 m values at report centres (m from the start, in the direction
    driven). `sfc_*` are the measured values (per track and their mean), `sfc_model` the noiseless model value."""

    station_m: np.ndarray
    sfc_left: np.ndarray
    sfc_right: np.ndarray
    sfc_model: np.ndarray
    fy_n: np.ndarray  # measured sideway force of the mean of the two wheels

    @property
    def sfc(self) -> np.ndarray:
        return 0.5 * (self.sfc_left + self.sfc_right)

    @property
    def mean_sfc(self) -> float:
        return float(np.mean(self.sfc))


@dataclass(frozen=True)
class SidewayForceWheel:
    """The test wheel and how it samples; SI units, angles in radians."""

    slip_angle_rad: float = field(default=SCRIM_SLIP_ANGLE_RAD, metadata=bounded(0.0, math.pi / 2, low_open=True))
    speed_mps: float = field(default=SCRIM_SPEED_MPS, metadata=bounded(0.0, 40.0, low_open=True))
    load_n: float = field(default=SCRIM_LOAD_N, metadata=bounded(0.0, 20000.0, low_open=True))
    sample_period_s: float = field(default=0.1, metadata=bounded(0.0, 10.0, low_open=True))
    report_length_m: float = field(default=SCRIM_REPORT_LENGTH_M, metadata=bounded(0.0, 1000.0, low_open=True))
    run_bias_share: float = field(default=SFC_RUN_BIAS_SHARE, metadata=bounded(0.0, 0.5))
    report_noise: float = field(default=SFC_REPORT_NOISE, metadata=bounded(0.0, 0.5))
    surface: str = "wet_asphalt"

    def __post_init__(self):
        check_bounds(self)
        check_choice("SidewayForceWheel", "surface", self.surface, set(SURFACES))

    @property
    def sample_spacing_m(self) -> float:
        return self.speed_mps * self.sample_period_s

    def sfc(self, mu_road) -> np.ndarray:
        """Noiseless SFC on a road of adhesion coefficient mu_road (array)."""
        return burckhardt_sfc(mu_road, self.slip_angle_rad, self.surface)

    def sideway_force_n(self, mu_road) -> np.ndarray:
        """F_y = mu(sin alpha) F_z on the test wheel, N."""
        return self.sfc(mu_road) * self.load_n

    def survey(self, mu_wet: MuProfile, length_m: float, rng: np.random.Generator) -> SfcSurvey:
        """Drive the test vehicle over [0, length_m] of a wetted road whose adhesion coefficient is `mu_wet` (stations
        in the direction driven): samples every sample_spacing_m, averaged per report length, with the run's bias and
        each value's noise from `rng`."""
        if not length_m >= self.report_length_m:
            raise ValueError(f"survey length_m must be >= report_length_m={self.report_length_m}, got {length_m!r}")
        n_reports = int(length_m // self.report_length_m)
        stations = np.arange(0.5 * self.sample_spacing_m, n_reports * self.report_length_m, self.sample_spacing_m)
        report = (stations // self.report_length_m).astype(np.int64)
        counts = np.bincount(report, minlength=n_reports)
        bias = 1.0 + rng.normal(0.0, self.run_bias_share)  # one per run: shared by both wheels
        per_track, models = [], []
        for track in TRACKS:
            force_n = self.sideway_force_n(mu_wet.at(stations, left=track == "left"))
            sfc = np.bincount(report, force_n / self.load_n, n_reports) / counts  # SFC = F_y / F_z, 10 m means
            models.append(sfc)
            per_track.append(sfc * bias + rng.normal(0.0, self.report_noise, n_reports))
        centres = (np.arange(n_reports) + 0.5) * self.report_length_m
        mean = 0.5 * (per_track[0] + per_track[1])
        return SfcSurvey(centres, per_track[0], per_track[1], 0.5 * (models[0] + models[1]), mean * self.load_n)
