"""pmf under braking without a controller: every wheel brakes, so no axle is a reference, but the fixed brake split
loads the axles unequally and the axle nearer its limit slips faster than its force. The slip between the front and
the rear axle, beyond the car's own braking line learned in gentle stops, tells mu; where both axles are linear it
says nothing of it."""

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
DRIVES = {"fwd": 1.0, "rwd": 0.0, "awd": 0.5}
STOP_AT_S = 120.0  # the stop under test begins here


def first_axle_decel(vehicle, share_of_limit, mu):
    """The deceleration (m/s^2) at which the axle the brake split loads most carries share_of_limit of mu (static
    loads: the transfer is left out, so the real share is a little larger on the front axle)."""
    psi = vehicle.cg_to_rear_axle_m / vehicle.wheelbase_m
    s = vehicle.brake_front_share
    return share_of_limit * mu / max(s / psi, (1.0 - s) / (1.0 - psi)) * G_MPS2


def _speed(brake_s):
    """Calm driving at 20 m/s on dry asphalt with three gentle stops to 16 m/s (1.3 m/s^2, 3 s each: the braking
    line's calibration), then the stop under test from STOP_AT_S: to 14 m/s in brake_s. Returns the profile and the
    distance driven before that stop."""
    t, v = [0.0, 40.0], [20.0, 20.0]
    for _ in range(3):
        t += [t[-1] + 3.0, t[-1] + 7.0, t[-1] + 13.0]
        v += [16.0, 20.0, 20.0]
    t += [STOP_AT_S, STOP_AT_S + brake_s, STOP_AT_S + brake_s + 10.0]
    v += [20.0, 14.0, 14.0]
    return SpeedProfile(t, v), float(np.trapezoid(v[:-2], t[:-2]))


def stop_estimates(car, profile_entry, tire, mu, share_of_limit, channels=False):
    """The drive of `_speed` on a straight road whose last part (from 30 m before the stop) has mu, the stop's
    deceleration putting the first axle at share_of_limit of mu by the catalogue's geometry, every production effect
    on (and every optional channel where `channels`). Returns pmf's estimates over the stop, given the catalogue
    profile."""
    brake_s = 6.0 / first_axle_decel(profile_entry, share_of_limit, mu)
    speed, before = _speed(brake_s)
    scenario = Scenario(
        run_id="stop",
        path=Path.straight(4000.0),
        mu=MuProfile([0.0, before - 30.0], [0.95, mu], [0.95, mu]),
        speed=speed,
        vehicle=car,
        tire=tire,
        duration_s=round(STOP_AT_S + brake_s + 6.0, 1),
        seed=5,
        effects=ProductionEffects.production().with_channels() if channels else ProductionEffects.production(),
    )
    run = simulate([scenario])
    out = pmf.PMFEstimator().estimate_batch(
        run, np.zeros(run.num_rows, dtype=np.int64), catalogue_profile(profile_entry, car)
    )
    t = (out["timestamp_ms"].to_numpy() - out["timestamp_ms"].to_numpy()[0]) / 1000.0
    braking = (t > STOP_AT_S) & (t < STOP_AT_S + brake_s)
    return {k: out[k].to_numpy()[braking] for k in ("mu", "mu_lower", "mu_upper")}


def drawn_car(entry, drive, front_load):
    """A car drawn around a catalogue entry: the drive layout given, 10 % more mass, its static front load share
    front_load off the catalogue's (the random vehicles span +-0.075; ECE R13-H's laden against unladen is 0.05).
    Returns (the car, the catalogue entry it registers as)."""
    catalogue = entry.replace(drive=drive, front_drive_share=DRIVES[drive])
    psi = catalogue.cg_to_rear_axle_m / catalogue.wheelbase_m + front_load
    car = catalogue.replace(
        name="drawn", mass_kg=1.1 * catalogue.mass_kg, cg_to_front_axle_m=(1.0 - psi) * catalogue.wheelbase_m
    )
    return car, catalogue


@pytest.mark.parametrize("tire, median_at_most", [("dugoff", 0.3), ("magic-formula", 0.7)])
@pytest.mark.parametrize("mu", [0.15, 0.2])
@pytest.mark.parametrize("drive", DRIVES)
@pytest.mark.parametrize("entry", [COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV], ids=["hatchback", "sedan", "suv"])
def test_gentle_braking_on_ice_reads_low(entry, drive, mu, tire, median_at_most):
    """A car drawn with its front 0.06 lighter than the catalogue says brakes on ice at about 0.1 g after calm driving
    with three gentle stops on dry asphalt: its front axle works at about 0.97 of the limit, no controller acts and no
    wheel is past its peak, so before this term only the bound spoke (median 0.75). The front axle slips faster than
    the braking line learned in the gentle stops: over the last second the median reads ice on the Dugoff tire (2.5
    to 5 times its linear slip there) and below the prior's on the Magic Formula's, whose curve is straighter (the
    brush model reads part of its bend as a softer tire); the interval holds the truth throughout, to the grid's
    resolution (half a step: its ends are read between the grid's cells)."""
    car, catalogue = drawn_car(entry, drive, -0.06)
    est = stop_estimates(car, catalogue, TIRES[tire], mu, 0.9)
    assert np.median(est["mu"][-10:]) <= median_at_most
    half_step = 0.5 * (pmf.MU_GRID[1] - pmf.MU_GRID[0])
    assert ((est["mu_lower"] <= mu + half_step) & (est["mu_upper"] >= mu - half_step)).all()


@pytest.mark.parametrize("drive", DRIVES)
@pytest.mark.parametrize("entry", [COMPACT_HATCHBACK, MIDSIZE_SEDAN, PAPER_SUV], ids=["hatchback", "sedan", "suv"])
def test_gentle_braking_on_ice_reads_low_with_the_gnss_reference_sent_too(entry, drive):
    """The same stops with every optional channel sent (GNSS speed, the forces, the steering torques): the braking
    term still reads the wheels under braking. Where the GNSS reference's per-axle terms read them instead (before
    this), against a line learned in calm driving rather than the car's own braking line, 4 of these 9 stops read
    0.47-0.60 (median of the last second)."""
    car, catalogue = drawn_car(entry, drive, -0.06)
    est = stop_estimates(car, catalogue, TIRES["dugoff"], 0.15, 0.9, channels=True)
    assert np.median(est["mu"][-10:]) <= 0.3
    assert ((est["mu_lower"] <= 0.15) & (est["mu_upper"] >= 0.15)).all()


@pytest.mark.parametrize("tire", TIRES)
@pytest.mark.parametrize("drive", DRIVES)
@pytest.mark.parametrize("front_load", [-0.06, 0.06], ids=["lighter-front", "heavier-front"])
@pytest.mark.parametrize("entry", [PAPER_SUV, COMPACT_HATCHBACK], ids=["suv", "hatchback"])
def test_braking_on_wet_and_dry_with_another_load_share_is_not_read_as_ice(entry, front_load, drive, tire):
    """Cars drawn with their static front load share 0.06 off the catalogue's, each drive layout, brake on wet (0.5)
    and dry (0.95) asphalt with their first axle at 0.5 and 0.85 of the limit: the split loads the axles otherwise
    than the profile says. Read against the catalogue's line at every sample, that read wet asphalt as snow (median
    0.34-0.37); against a line whose zero and slope were taken from a 2WD's slip line, as 0.32-0.45 (a 0.002-0.005
    error in the zero, extrapolated). The median stays above 0.6 and the upper end above 0.8."""
    car, catalogue = drawn_car(entry, drive, front_load)
    for mu, share_of_limit in ((0.5, 0.5), (0.5, 0.85), (0.95, 0.5), (0.95, 0.85)):
        est = stop_estimates(car, catalogue, TIRES[tire], mu, share_of_limit)
        assert est["mu"].min() >= 0.6, (mu, share_of_limit)
        assert est["mu_upper"].min() >= 0.8, (mu, share_of_limit)


def test_slip_between_linear_axles_says_nothing_of_mu():
    """Both axles in the brush model's linear range (forces per load 0.05 and 0.04, a quarter of the lowest mu read
    here): the difference of their slips is (f_front - f_rear) / C whatever mu, so the likelihood is flat over mu for
    each stiffness, and it is the stiffness that the measured difference picks."""
    c0 = 20.0
    like = np.empty((pmf.NM, pmf.NC))
    d = (0.05 - 0.04) / c0  # the difference of a tire at the profile's stiffness
    pmf._brake_slip_likelihood(d, 0.03, 0.05, 0.04, 0.05, 0.04, 0.7, 0.6, 0.05, 20.0, c0, c0, 0.0, np.nan, 10.0, like)
    above = pmf.MU_GRID >= 0.2
    assert (like[above].min(axis=0) >= 0.97 * like[above].max(axis=0)).all()
    assert np.argmax(like[above].mean(axis=0)) == np.argmin(abs(pmf.C_FACTORS - 1.0))


def test_an_axle_near_its_limit_speaks_against_a_high_mu_louder_once_the_line_is_learned():
    """The front axle at 0.9 of mu 0.2 (f 0.18), the rear at 0.1: the brush model's difference of slips, measured, is
    most likely at mu 0.2 and less so on dry asphalt, whose slips are linear. Before the braking line is learned, the
    car's split and load share (the same at every sample, so counted once over the grid's memory) could make the same
    difference on dry asphalt, and one tempered sample says little; with the line known, the slip beyond it is the
    curve's alone and the same sample speaks several times louder."""
    c0 = 20.0
    d = pmf.brush_slip(0.18, 0.2, c0) - pmf.brush_slip(0.1, 0.2, c0)
    near, dry = np.argmin(abs(pmf.MU_GRID - 0.2)), np.argmin(abs(pmf.MU_GRID - 0.9))
    j = np.argmin(abs(pmf.C_FACTORS - 1.0))
    ratio = {}
    for name, line, line_var in (("catalogue", 0.0, np.nan), ("learned", (0.18 - 0.1) / c0, 1e-8)):
        like = np.empty((pmf.NM, pmf.NC))
        pmf._brake_slip_likelihood(
            d, 0.08, 0.18, 0.1, 0.18, 0.1, 0.7, 0.6, 0.05, 20.0, c0, c0, line, line_var, 10.0, like
        )
        assert like[near, j] >= 0.99
        ratio[name] = like[dry, j] / like[near, j]
    assert ratio["learned"] <= 0.85 and 1.0 - ratio["learned"] >= 3.0 * (1.0 - ratio["catalogue"])


@pytest.mark.parametrize("entry", [COMPACT_HATCHBACK, PAPER_SUV], ids=["hatchback", "suv"])
def test_a_car_standing_on_the_ice_it_stopped_on_keeps_knowing_it(entry):
    """An ABS stop from 20 m/s on ice (mu 0.15) after calm driving on dry asphalt, then standing on the ice: the stop
    proves mu to within a few tenths, and standing on the same metres changes nothing of it, so 20 s after the stop
    mu_upper stays below 0.45 with the truth inside. While the grid forgot with time alone, 20 s standing took it back
    to the prior (mu_upper above 1)."""
    t = [0.0, 40.0, 40.0 + 20.0 / 3.0, 120.0]
    speed = SpeedProfile(t, [20.0, 20.0, 0.0, 0.0])
    before = 20.0 * 40.0
    scenario = Scenario(
        run_id="stand",
        path=Path.straight(2000.0),
        mu=MuProfile([0.0, before - 30.0], [0.95, 0.15], [0.95, 0.15]),
        speed=speed,
        vehicle=entry,
        duration_s=100.0,
        seed=5,
        effects=ProductionEffects.production(),
    )
    run = simulate([scenario])
    out = pmf.PMFEstimator().estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), entry)
    t_s = (out["timestamp_ms"].to_numpy() - out["timestamp_ms"].to_numpy()[0]) / 1000.0
    abs_on = run["abs_active"].to_numpy(zero_copy_only=False).astype(bool)
    assert abs_on.any()
    last = t_s[np.flatnonzero(abs_on)[-1]]
    standing = (t_s >= last + 2.0) & (t_s <= last + 20.0)
    assert standing.any() and (run["vx_true_mps"].to_numpy()[standing] < 0.1).all()
    upper, lower = out["mu_upper"].to_numpy()[standing], out["mu_lower"].to_numpy()[standing]
    assert upper.max() < 0.45, upper.max()
    assert (lower <= 0.15).all() and (upper >= 0.15).all()


def test_a_firm_drivers_stops_on_dry_asphalt_are_not_read_as_ice():
    """A fleet car whose driver brakes firmly (0.3 g; the fleet benchmark's tuning seed 100, vehicle bench-010, a
    midsize sedan on Dugoff tires) passes through gentle braking only in a stop's first or last sample (one sample
    mixes the force before and after the step: the signal groups are read apart), and once leaving an ice patch
    with its wheels still slipping. A braking line learned from those samples took k_b ten times the catalogue's and
    read its firm stops on dry asphalt as ice: 68 samples with mu_upper below 0.5 in its first 51 minutes. Learned
    only where braking has held its conditions for LINE_SETTLE_S, none reads so (one sample, leaving the patch,
    carries its reading)."""
    from roadgrip.evaluation.fleet_benchmark import make_scenario, vehicle_drive

    fleet = make_scenario(100)
    run, trips = vehicle_drive(fleet, "bench-010", until_s=3060.0)
    out = pmf.PMFEstimator().estimate_batch(run, trips, fleet.kinds["bench-010"])
    dry = run["mu"].to_numpy() >= 0.6
    firm = run["ax_true_mps2"].to_numpy() < -2.5
    assert (dry & firm).sum() > 300
    assert ((out["mu_upper"].to_numpy() < 0.5) & dry).sum() <= 1
