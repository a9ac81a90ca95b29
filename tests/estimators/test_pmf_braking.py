"""pmf under braking without a controller: every wheel brakes, so no axle is a reference, but the fixed brake split loads
the axles unequally and the axle nearer its limit slips faster than its force. The slip between the front and the rear
axle then tells mu where the tire's stiffness is calibrated, and says nothing of it where both axles are linear."""

import numpy as np
import pytest

from roadgrip.estimators import pmf
from roadgrip.evaluation.bins import catalogue_profile
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV
from roadgrip.vehicle.tires.dugoff import DugoffTire
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

TIRES = {"dugoff": DugoffTire(), "magic-formula": MagicFormulaTire()}
CRUISE_S = 60.0  # calm driving on dry asphalt before the stop: the slip line and the radius ratios calibrate
DRIVES = {"fwd": 1.0, "rwd": 0.0, "awd": 0.5}


def _first_axle_decel(vehicle, share_of_limit, mu):
    """The deceleration (m/s^2) at which the axle the brake split loads most carries share_of_limit of mu (static
    loads: the transfer is left out, so the real share is a little larger on the front axle)."""
    psi = vehicle.cg_to_rear_axle_m / vehicle.wheelbase_m
    s = vehicle.brake_front_share
    return share_of_limit * mu / max(s / psi, (1.0 - s) / (1.0 - psi)) * G_MPS2


def _stop(car, profile_entry, tire, mu, share_of_limit):
    """A cruise at 20 m/s on dry asphalt, then a road of mu where the car brakes to 14 m/s at a steady deceleration
    (the first axle at share_of_limit of mu by the catalogue's geometry), every production effect on. Returns pmf's
    estimates over the braking, given the catalogue profile."""
    decel = _first_axle_decel(profile_entry, share_of_limit, mu)
    brake_s = 6.0 / decel
    scenario = Scenario(
        run_id="stop",
        path=Path.straight(3000.0),
        mu=MuProfile([0.0, 20.0 * CRUISE_S - 50.0], [0.95, mu], [0.95, mu]),
        speed=SpeedProfile([0.0, CRUISE_S, CRUISE_S + brake_s, CRUISE_S + brake_s + 10.0], [20.0, 20.0, 14.0, 14.0]),
        vehicle=car,
        tire=tire,
        duration_s=round(CRUISE_S + brake_s + 6.0, 1),
        seed=5,
        effects=ProductionEffects.production(),
    )
    run = simulate([scenario])
    out = pmf.PMFEstimator().estimate_batch(
        run, np.zeros(run.num_rows, dtype=np.int64), catalogue_profile(profile_entry, car)
    )
    t = (out["timestamp_ms"].to_numpy() - out["timestamp_ms"].to_numpy()[0]) / 1000.0
    braking = (t > CRUISE_S) & (t < CRUISE_S + brake_s)
    return {k: out[k].to_numpy()[braking] for k in ("mu", "mu_lower", "mu_upper")}


@pytest.mark.parametrize("tire, median_at_most", [("dugoff", 0.45), ("magic-formula", 0.7)])
@pytest.mark.parametrize("mu", [0.15, 0.2])
@pytest.mark.parametrize(
    "entry",
    [COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV.replace(drive="fwd", front_drive_share=1.0)],
    ids=["hatchback", "sedan", "suv-fwd"],
)
def test_gentle_braking_on_ice_reads_low_on_a_calibrated_car(entry, mu, tire, median_at_most):
    """A front-driven car (its slip line, so its tires' stiffness, calibrated in the cruise) brakes on ice at 0.1 g,
    its front axle at 0.9 of the limit: no controller acts and no wheel is past its peak, so before this term only the
    bound spoke (median 0.75). The front axle slips faster than its force, the rear does not: over the last second
    the median reads below wet asphalt on the Dugoff tire (2.5 times its linear slip at 0.9 of the limit) and below
    the prior's on the Magic Formula's, whose curve is straighter there (the brush model reads part of its bend as a
    softer tire); the interval holds the truth throughout."""
    est = _stop(entry, entry, TIRES[tire], mu, 0.9)
    assert np.median(est["mu"][-10:]) <= median_at_most
    assert ((est["mu_lower"] <= mu) & (est["mu_upper"] >= mu)).all()


@pytest.mark.parametrize("tire", TIRES)
@pytest.mark.parametrize("drive", DRIVES)
@pytest.mark.parametrize("front_load", [-0.06, 0.06], ids=["lighter-front", "heavier-front"])
@pytest.mark.parametrize("entry", [PAPER_SUV, MIDSIZE_SEDAN], ids=["suv", "sedan"])
def test_braking_on_wet_and_dry_with_another_load_share_is_not_read_as_ice(entry, front_load, drive, tire):
    """Cars drawn with 10 % more mass and their static front load share 0.06 off the catalogue's (the random
    vehicles' span; ECE R13-H's laden against unladen is 0.05), each drive layout, braking on wet (0.5) and dry (0.95)
    asphalt with their first axle at 0.5 and 0.85 of the limit: the split then loads the axles otherwise than the
    profile says, which the first version of this term, counting that error once a sample, read as snow on wet
    asphalt (median 0.34-0.37). The median stays above 0.45 and the upper end above 0.8."""
    catalogue = entry.replace(drive=drive, front_drive_share=DRIVES[drive])
    psi = catalogue.cg_to_rear_axle_m / catalogue.wheelbase_m + front_load
    car = catalogue.replace(
        name="drawn", mass_kg=1.1 * catalogue.mass_kg, cg_to_front_axle_m=(1.0 - psi) * catalogue.wheelbase_m
    )
    for mu, share_of_limit in ((0.5, 0.5), (0.5, 0.85), (0.95, 0.85)):
        est = _stop(car, catalogue, TIRES[tire], mu, share_of_limit)
        assert est["mu"].min() >= 0.45, (mu, share_of_limit)
        assert est["mu_upper"].min() >= 0.8, (mu, share_of_limit)


def test_slip_between_linear_axles_says_nothing_of_mu():
    """Both axles in the brush model's linear range (forces per load 0.05 and 0.04, a quarter of the lowest mu read
    here): the difference of their slips is (f_front - f_rear) / C whatever mu, so the likelihood is flat over mu for
    each stiffness, and it is the stiffness that the measured difference picks."""
    c0 = 20.0
    like = np.empty((pmf.NM, pmf.NC))
    d = (0.05 - 0.04) / c0  # the difference of a tire at the profile's stiffness
    pmf._brake_slip_likelihood(d, 0.05, 0.04, 0.7, 0.6, 0.05, 20.0, c0, c0, 10.0, like)
    above = pmf.MU_GRID >= 0.2
    assert (like[above].min(axis=0) >= 0.97 * like[above].max(axis=0)).all()
    assert np.argmax(like[above].mean(axis=0)) == np.argmin(abs(pmf.C_FACTORS - 1.0))


def test_an_axle_near_its_limit_speaks_against_a_high_mu():
    """The front axle at 0.97 of mu 0.2 (f 0.194), the rear at 0.1: the brush model's difference of slips, measured,
    is most likely at mu near 0.2, and dry asphalt's linear slips fall short of it. One tempered sample, with the
    car's split and load share counted once over the grid's memory, says so mildly (the grid hears about ten)."""
    c0 = 20.0
    d = pmf.brush_slip(0.194, 0.2, c0) - pmf.brush_slip(0.1, 0.2, c0)
    like = np.empty((pmf.NM, pmf.NC))
    pmf._brake_slip_likelihood(d, 0.194, 0.1, 0.7, 0.6, 0.05, 20.0, c0, c0, 10.0, like)
    j = np.argmin(abs(pmf.C_FACTORS - 1.0))
    near = like[np.argmin(abs(pmf.MU_GRID - 0.2)), j]
    dry = like[np.argmin(abs(pmf.MU_GRID - 0.9)), j]
    assert near >= 0.99 and dry <= 0.85 * near
