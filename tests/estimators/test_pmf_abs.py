"""pmf under ABS: the brake demand is unknown, so ABS tells mu between the car's utilisation (both axles at their limit)
and the utilisation of the axle the profile's brake split saturates first (only that one at its limit)."""

import numpy as np
import pyarrow.compute as pc
import pytest

from roadgrip.estimators import pmf
from roadgrip.evaluation.bins import catalogue_profile
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile, Path
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import COMPACT_HATCHBACK, PAPER_SUV
from roadgrip.vehicle.tires.dugoff import DugoffTire
from roadgrip.vehicle.tires.magic_formula import MagicFormulaTire

ENTRIES = {"suv": PAPER_SUV, "hatchback": COMPACT_HATCHBACK}
DRAWN_FRONT_LOAD = {"suv": 0.45, "hatchback": 0.55}  # the drawn cars' static front load share (catalogue 0.48, 0.62)
TIRES = {"dugoff": DugoffTire(), "magic-formula": MagicFormulaTire()}
MUS = (0.3, 0.95)  # snow, dry asphalt


def _axle_utilisations(vehicle, decel_mps2):
    """(front, rear) force per load of a car braking at decel_mps2 in a straight line with its fixed brake split, the
    loads with the longitudinal transfer m a h / L (each at least 0.2 of the weight, as pmf takes them)."""
    wb, h = vehicle.wheelbase_m, vehicle.cg_height_m
    front_load = max((vehicle.cg_to_rear_axle_m + decel_mps2 / G_MPS2 * h) / wb, 0.2)
    rear_load = max((vehicle.cg_to_front_axle_m - decel_mps2 / G_MPS2 * h) / wb, 0.2)
    f = decel_mps2 / G_MPS2
    return vehicle.brake_front_share * f / front_load, (1.0 - vehicle.brake_front_share) * f / rear_load


def _drawn(name):
    entry = ENTRIES[name]
    return entry.replace(
        name=f"{name}-drawn",
        mass_kg=1.1 * entry.mass_kg,
        cg_to_front_axle_m=(1.0 - DRAWN_FRONT_LOAD[name]) * entry.wheelbase_m,
    )


@pytest.fixture(scope="module")
def stops():
    """Stops from 25 m/s asking for 1.2 mu g (ABS on for most of them), each car drawn around a catalogue entry with
    another load share and mass, every production effect on; run id -> (run, catalogue profile, mu)."""
    scenarios, profiles = [], {}
    for name, entry in ENTRIES.items():
        for tire_name, tire in TIRES.items():
            for mu in MUS:
                brake_s = 25.0 / (1.2 * mu * G_MPS2)
                run_id = f"{name}-{tire_name}-{mu}"
                scenarios.append(
                    Scenario(
                        run_id=run_id,
                        path=Path.straight(600.0),
                        mu=MuProfile.uniform(mu),
                        speed=SpeedProfile([0.0, 2.0, 2.0 + brake_s, 4.0 + brake_s], [25.0, 25.0, 0.0, 0.0]),
                        vehicle=_drawn(name),
                        tire=tire,
                        duration_s=round(4.0 + brake_s, 1),
                        seed=7,
                        effects=ProductionEffects.production(),
                    )
                )
                profiles[run_id] = (catalogue_profile(entry, scenarios[-1].vehicle), mu)
    table = simulate(scenarios)
    return {k: (table.filter(pc.equal(table["run_id"], k)), *v) for k, v in profiles.items()}


@pytest.mark.parametrize("run_id", [f"{n}-{t}-{mu}" for n in ENTRIES for t in TIRES for mu in MUS])
def test_abs_stop_brackets_mu_within_what_the_brake_split_leaves_open(stops, run_id):
    """Over the ABS samples of a stop (above 5 m/s) the 90 % interval holds the true mu, and the median is within half
    the range ABS leaves open at the limit (from u_car = mu to u_first: the first axle's utilisation at a deceleration
    of mu g, by the catalogue profile) plus 0.03 (the slip band's brush force against the tire's). The reading before
    issue 23 put mu where the first axle's force by the brake split is the peak: 0.22-0.43 too high on dry asphalt."""
    run, profile, mu = stops[run_id]
    out = pmf.PMFEstimator().estimate_batch(run, np.zeros(run.num_rows, dtype=np.int64), profile)
    at = run["abs_active"].to_numpy(zero_copy_only=False) & (run["vx_true_mps"].to_numpy() > 5.0)
    assert at.sum() >= 15
    est, lower, upper = (out[c].to_numpy()[at] for c in ("mu", "mu_lower", "mu_upper"))
    assert np.mean((lower <= mu) & (mu <= upper)) >= 0.9
    u_first = max(_axle_utilisations(profile, mu * G_MPS2))
    assert abs(np.median(est) - mu) <= 0.5 * (u_first - mu) + 0.03


def _likelihood(u_car, u_first, s_u=0.02):
    """The ABS likelihood over mu at the profile's stiffness (the grid's C factor nearest 1), peak-normalised."""
    like = np.empty((pmf.NM, pmf.NC))
    s_first = s_u * u_first / u_car
    pmf._abs_likelihood(u_car, s_u, u_first, s_first, PAPER_SUV.tire_front.longitudinal_stiffness_per_load, like)
    lk = like[:, int(np.argmin(np.abs(np.log(pmf.C_FACTORS))))]
    return lk / lk.max()


def _at(lk, mu):
    return lk[int(np.argmin(np.abs(pmf.MU_GRID - mu)))]


@pytest.mark.parametrize("mu", [0.3, 0.9])
def test_both_axles_at_the_limit_and_only_the_first_both_explain_the_true_mu(mu):
    """Closed form, the paper SUV. Both axles at their limit: the car decelerates at mu g, u_car = mu and the profile's
    split names an axle at u_first > mu. Only the first axle at its limit: the deceleration a at which that axle's
    force per load by the split is mu, so u_first = mu and u_car = a / g < mu. Either way the likelihood is high
    within 0.05 of the true mu (ABS holds its slip band, where a stiff tire's force is 0.95-1 of its peak), peaks in
    [u_car, u_first] (widened by 0.05 likewise), and is low 0.1 below u_car (the tires' force bound) and 0.2 above
    u_first (no axle there: only a soft tire at high mu holds so little in the band)."""
    both = (mu, max(_axle_utilisations(PAPER_SUV, mu * G_MPS2)))
    decel = mu * G_MPS2 * np.linspace(0.5, 1.0, 5001)
    first = [max(_axle_utilisations(PAPER_SUV, a)) for a in decel]
    a_first = decel[int(np.argmin(np.abs(np.array(first) - mu)))]
    only_first = (a_first / G_MPS2, mu)
    for u_car, u_first in (both, only_first):
        assert u_car <= mu <= u_first and u_first - u_car > 0.04 * mu
        lk = _likelihood(u_car, u_first)
        assert lk[np.abs(pmf.MU_GRID - mu) <= 0.05 + 1e-9].max() >= 0.5
        assert u_car - 0.05 <= pmf.MU_GRID[int(np.argmax(lk))] <= u_first + 0.05
        assert _at(lk, u_car - 0.1) <= 0.05 and _at(lk, u_first + 0.2) <= 0.4
