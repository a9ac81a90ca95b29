import math

import numpy as np
import pytest

from roadgrip.evaluation.sideway_force import (
    SCRIM_SLIP_ANGLE_RAD,
    SidewayForceWheel,
    burckhardt_sfc,
    free_rolling_slip,
)
from roadgrip.sim.roads import MuProfile
from roadgrip.vehicle.params import TireParams
from roadgrip.vehicle.tires import BurckhardtTire
from roadgrip.vehicle.tires.burckhardt import SURFACES, peak_mu


def test_sfc_of_tabulated_wet_asphalt_is_the_closed_form_at_sin_20_degrees():
    c1, c2, c3 = 0.857, 33.822, 0.347  # wet asphalt, Burckhardt 1993 (roadgrip/vehicle/tires/burckhardt_surfaces.csv)
    s = math.sin(math.radians(20.0))
    expected = c1 * (1.0 - math.exp(-c2 * s)) - c3 * s
    wheel = SidewayForceWheel()
    assert wheel.slip_angle_rad == pytest.approx(math.radians(20.0))
    assert float(wheel.sfc(peak_mu(c1, c2, c3))) == pytest.approx(expected, rel=1e-12)
    assert expected == pytest.approx(0.738, abs=5e-4)


def test_free_rolling_wheel_slides_at_sin_alpha_perpendicular_to_its_plane():
    s_x, s_y, s = free_rolling_slip(np.radians([0.0, 20.0, 90.0]))
    np.testing.assert_allclose(s_x, 0.0)
    np.testing.assert_allclose(s_y, [0.0, math.sin(math.radians(20.0)), 1.0])
    np.testing.assert_allclose(s, s_y)


@pytest.mark.parametrize("surface", sorted(set(SURFACES) - {"ice"}))
def test_sfc_at_20_degrees_is_below_the_peak_mu(surface):
    """Past the peak of the curve the sliding test wheel gets less than the road's adhesion coefficient (ice has no
    falling branch, c3 = 0, so there SFC reaches the peak)."""
    mu_road = np.linspace(0.05, 1.4, 28)
    sfc = burckhardt_sfc(mu_road, SCRIM_SLIP_ANGLE_RAD, surface)
    assert (sfc < mu_road).all() and (sfc > 0.0).all()
    np.testing.assert_allclose(sfc / mu_road, sfc[0] / mu_road[0])  # proportional to the road's mu


def test_sfc_is_zero_without_slip_and_never_exceeds_mu():
    assert float(burckhardt_sfc(0.8, 0.0)) == 0.0
    angles = np.radians(np.linspace(0.5, 90.0, 60))
    sfc = np.array([float(burckhardt_sfc(0.8, a)) for a in angles])
    assert (sfc <= 0.8 + 1e-12).all()
    peak_slip = 0.1308  # wet asphalt's peak: the SFC is largest at the slip angle whose sine it is
    assert sfc.argmax() == np.argmin(np.abs(np.sin(angles) - peak_slip))


@pytest.mark.parametrize("mu_road", [0.3, 0.8, 1.1])
def test_sfc_agrees_with_the_simulators_burckhardt_kernel(mu_road):
    """Second implementation: the simulator's kernel takes s_y = tan(alpha) C_y / C_x; with C_y / C_x = cos(alpha) that
    is sin(alpha), and at zero slip ratio its lateral force over the load must be our SFC."""
    alpha = SCRIM_SLIP_ANGLE_RAD
    tire = TireParams(20.0, 20.0 * math.cos(alpha))
    fx, fy = (np.ravel(f)[0] for f in BurckhardtTire("wet_asphalt").forces(tire, 0.0, alpha, 1961.33, mu_road))
    assert fx == pytest.approx(0.0, abs=1e-9)
    assert fy / 1961.33 == pytest.approx(float(burckhardt_sfc(mu_road)), rel=1e-9)


def test_survey_without_scatter_reads_the_model_every_10_m():
    wheel = SidewayForceWheel(run_bias_share=0.0, report_noise=0.0)
    survey = wheel.survey(MuProfile.uniform(0.7), 1000.0, np.random.default_rng(0))
    assert survey.station_m.size == 100
    np.testing.assert_allclose(survey.station_m[:2], [5.0, 15.0])
    np.testing.assert_allclose(survey.sfc, float(wheel.sfc(0.7)))
    np.testing.assert_allclose(survey.fy_n, float(wheel.sfc(0.7)) * wheel.load_n)


def test_survey_averages_each_track_and_follows_the_road():
    wheel = SidewayForceWheel(run_bias_share=0.0, report_noise=0.0)
    ramp = MuProfile([0.0, 500.0], [0.4, 0.8], [0.6, 0.6], "linear")
    survey = wheel.survey(ramp, 500.0, np.random.default_rng(0))
    assert survey.sfc_left[0] < survey.sfc_left[-1]
    np.testing.assert_allclose(survey.sfc_right, float(wheel.sfc(0.6)))
    np.testing.assert_allclose(survey.sfc, 0.5 * (survey.sfc_left + survey.sfc_right))
    assert survey.mean_sfc == pytest.approx(float(wheel.sfc(0.6)), rel=2e-3)  # the ramp's mean is 0.6


def test_survey_scatter_is_seeded():
    wheel, road = SidewayForceWheel(), MuProfile.uniform(0.8)
    a, b = (wheel.survey(road, 2000.0, np.random.default_rng(3)) for _ in range(2))
    np.testing.assert_array_equal(a.sfc, b.sfc)
    c = wheel.survey(road, 2000.0, np.random.default_rng(4))
    assert not np.array_equal(a.sfc, c.sfc)
    assert abs(a.mean_sfc - float(wheel.sfc(0.8))) < 0.1


def test_bad_settings_name_the_field():
    with pytest.raises(ValueError, match="slip_angle_rad"):
        SidewayForceWheel(slip_angle_rad=0.0)
    with pytest.raises(ValueError, match="surface"):
        SidewayForceWheel(surface="gravel")
    with pytest.raises(ValueError, match="length_m"):
        SidewayForceWheel().survey(MuProfile.uniform(0.5), 5.0, np.random.default_rng(0))
