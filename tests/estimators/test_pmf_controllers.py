"""pmf under traction control: the controller holds the driven wheels' slip in a band, and the driven axle's force is
the tire's at a slip there: near the peak for a stiff tire, a fraction of it for a soft one (cobblestone, winter
tires). A soft tire starting on a dry road must not read as ice; a tire whose stiffness calm driving has shown still
reads ice from its start."""

import numpy as np
import pytest

from roadgrip.estimators import pmf
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, PAPER_SUV
from roadgrip.vehicle.tires.dugoff import DugoffTire

SOFT = 0.35  # a slip curve this soft (per unit of the catalogue's) is Burckhardt's dry cobblestone against dry asphalt
START_S = 10.0  # the start under test lasts this long


def start_estimates(stiffness_scale, mu, calm_s, vehicle=COMPACT_HATCHBACK):
    """A compact hatchback (front drive; or `vehicle`) on Dugoff tires of the given stiffness scale, every production effect on:
    calm_s seconds of calm driving (10-18 m/s, gentle changes) on a straight road of friction mu, a stop, then a start
    from 2 m/s asking 1.3 mu g (traction control acts on most of it). Returns the estimates over the start's last
    START_S seconds and the share of them with traction control acting."""
    rng = np.random.default_rng(1)
    t, v = [0.0], [12.0]
    while t[-1] < calm_s:
        t.append(t[-1] + rng.uniform(8.0, 15.0))
        v.append(rng.uniform(10.0, 18.0))
    start = t[-1] + 25.0
    t += [t[-1] + 20.0, start, start + 25.0 / (1.3 * mu * G_MPS2), start + 200.0]
    v += [2.0, 2.0, 27.0, 27.0]
    scenario = Scenario(
        "start",
        Path.straight(8000.0),
        MuProfile.uniform(mu),
        SpeedProfile(t, v),
        vehicle=vehicle,
        tire=DugoffTire(stiffness_scale=stiffness_scale),
        duration_s=start + START_S,
        seed=3,
        effects=ProductionEffects.production(),
    )
    run = simulate([scenario])
    out = pmf.PMFEstimator().estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), vehicle)
    last = slice(-int(START_S * 10), None)
    tcs = run["tcs_active"].to_numpy(zero_copy_only=False).astype(bool)[last]
    return {c: out[c].to_numpy()[last] for c in ("mu", "mu_lower", "mu_upper")}, tcs.mean()


@pytest.mark.parametrize("calm_s", [0.0, 120.0])
def test_a_soft_tire_under_traction_control_is_not_read_as_ice(calm_s):
    """The soft tire's slip crosses the controller's threshold at about a tenth of a dry road's mu: the interval must
    keep the road's 1.0 (the earlier reading, u_axle / mu above 0.3, put mu_upper near 0.6 and excluded it)."""
    out, tcs = start_estimates(SOFT, 1.0, calm_s)
    assert tcs > 0.5
    assert out["mu_upper"].min() >= 1.0
    assert (out["mu_lower"] <= 1.0).all()


def test_a_calibrated_tire_under_traction_control_reads_ice():
    """Two minutes of calm driving show the catalogue tire's stiffness: its slip at the controller's threshold is then
    at its peak, and the start reads the ice."""
    out, tcs = start_estimates(1.0, 0.15, 120.0)
    assert tcs > 0.5
    assert out["mu_upper"][-20:].max() < 0.3
    assert (out["mu_lower"] <= 0.15).all()


def test_an_unknown_tire_under_traction_control_leaves_ice_and_dry_open():
    """A fresh start on ice with nothing known of the tire: a saturated stiff tire and a soft one far below its peak
    hold the same force at the controller's slip, so the interval spans both (never a confident number)."""
    out, _ = start_estimates(1.0, 0.15, 0.0)
    assert out["mu_lower"][-1] <= 0.15 and out["mu_upper"][-1] >= 0.9


def test_an_all_wheel_drive_car_without_a_gnss_speed_never_shows_its_stiffness():
    """The paper SUV drives all four wheels: no undriven axle to fit a slip line against, so two minutes of calm
    driving leave its stiffness unknown and a start on ice under traction control still leaves dry open (a limit of
    the channels, docs/ESTIMATORS.md 15)."""
    assert PAPER_SUV.drive == "awd"
    out, tcs = start_estimates(1.0, 0.15, 120.0, PAPER_SUV)
    assert tcs > 0.5
    assert out["mu_lower"][-1] <= 0.15 and out["mu_upper"][-1] >= 0.9


@pytest.mark.parametrize(("vehicle", "calm_s"), [(COMPACT_HATCHBACK, 0.0), (PAPER_SUV, 120.0)])
def test_traction_control_held_through_a_start_on_ice_does_not_wear_its_own_evidence_away(vehicle, calm_s):
    """Traction control on ice for the whole start, each sample saying what the last said (a low road, or a tire far
    softer than known): the median stays where the first seconds put it, it does not drift back to the prior's 0.78
    as the grid's forgetting redraws mu (docs/ESTIMATORS.md 14; before, from the second second to the last five: 0.61
    -> 0.73 on a new car, 0.36 -> 0.68 on the four-wheel-driven SUV after calm driving), and the interval keeps both
    readings open where the stiffness is not known."""
    out, tcs = start_estimates(1.0, 0.15, calm_s, vehicle)
    assert tcs > 0.5
    early = out["mu"][10:20].mean()  # the start's second second
    assert early < 0.65
    assert out["mu"][-50:].mean() <= early + 0.05
    assert (out["mu_lower"] <= 0.15).all() and out["mu_upper"][-1] >= 0.9


def test_the_band_puts_a_stiff_tire_at_its_peak_and_leaves_a_soft_one_open():
    """_tcs_likelihood at a driven axle's force per load of 0.2: the catalogue tire holds it only where mu is near
    0.2 (saturated in the band), the softest tire of the grid at any mu above it."""
    c0 = COMPACT_HATCHBACK.tire_front.longitudinal_stiffness_per_load
    like = np.empty((pmf.NM, pmf.NC))
    pmf._tcs_likelihood(0.2, 0.02, c0, like)
    stiff, soft = int(np.argmin(abs(pmf.C_FACTORS - 1.0))), 0
    at = {mu: int(np.argmin(abs(pmf.MU_GRID - mu))) for mu in (0.1, 0.2, 1.2)}
    assert like[at[1.2], stiff] < 1e-3
    assert like[at[0.2], stiff] > 0.2
    assert like[at[1.2], soft] > 0.5
    assert like[at[0.1], soft] < 1e-3 and like[at[0.1], stiff] < 1e-3
