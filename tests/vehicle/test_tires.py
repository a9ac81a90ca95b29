"""Tire models against their limits and closed forms: zero slip gives zero force, the force stays inside the friction
circle |F| <= mu F_z, the small-slip slope is the linear stiffness, the force saturates at the road's mu, the paper's
sign conventions, and the Burckhardt curves' closed-form peaks."""

import math

import numpy as np
import pytest

from roadgrip.vehicle.params import TireParams
from roadgrip.vehicle.tires import TIRE_MODELS, BurckhardtTire, DugoffTire, MagicFormulaTire, tire_model_by_name
from roadgrip.vehicle.tires.burckhardt import SURFACES, burckhardt_curve, peak_mu, peak_slip

TIRE = TireParams()  # C_x / F_z = 25, C_y / F_z = 16 1/rad
MODELS = [DugoffTire(), MagicFormulaTire(), BurckhardtTire(), BurckhardtTire("dry_asphalt")]
MODEL_IDS = ["dugoff", "magic-formula", "burckhardt-nearest-surface", "burckhardt-dry-asphalt"]
LINEAR_MODELS = [DugoffTire(), MagicFormulaTire(), MagicFormulaTire(shape_c=1.65, curvature_e=-0.5)]
LINEAR_IDS = ["dugoff", "magic-formula", "magic-formula-c1.65-e-0.5"]

# Burckhardt 1993 as tabulated in Kiencke & Nielsen, Automotive Control Systems (2nd ed., 2005), table 7.1
DRY_ASPHALT = (1.2801, 23.99, 0.52)
WET_ASPHALT = (0.857, 33.822, 0.347)


def closed_form_peak(c1, c2, c3):
    """Slip and value of the maximum of mu(s) = c1 (1 - exp(-c2 s)) - c3 s: d mu / ds = c1 c2 exp(-c2 s) - c3 = 0."""
    s_star = math.log(c1 * c2 / c3) / c2
    return s_star, c1 * (1.0 - math.exp(-c2 * s_star)) - c3 * s_star


def dense_grid():
    """Slip ratio in [-1, 1], slip angle in [-1.3, 1.3] rad, F_z in [0, 10 kN], mu in [0, 1.5]; edges and 0 included."""
    slip = np.unique(np.concatenate([np.linspace(-1.0, 1.0, 81), [-0.999, -1e-4, 1e-4, 0.999]]))
    alpha = np.unique(np.concatenate([np.linspace(-1.3, 1.3, 53), [-1e-4, 1e-4]]))
    fz = np.linspace(0.0, 10000.0, 11)
    mu = np.linspace(0.0, 1.5, 7)
    return np.meshgrid(slip, alpha, fz, mu, indexing="ij")


# --- zero slip, friction circle, signs (every model) ---------------------------------------------------------------


@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_zero_slip_gives_zero_force(model):
    fz = np.linspace(0.0, 10000.0, 21)[:, None]
    mu = np.linspace(0.0, 1.5, 16)[None, :]
    fx, fy = model.forces(TIRE, 0.0, 0.0, fz, mu)
    assert np.all(fx == 0.0)
    assert np.all(fy == 0.0)


@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_zero_load_or_zero_mu_gives_zero_force(model):
    slip, alpha, _, _ = dense_grid()
    slip, alpha = slip[..., 0, 0], alpha[..., 0, 0]
    for fz, mu in ((0.0, 0.9), (5000.0, 0.0)):
        fx, fy = model.forces(TIRE, slip, alpha, fz, mu)
        assert np.all(fx == 0.0) and np.all(fy == 0.0)


@pytest.mark.parametrize(
    "tire", [TIRE, TireParams(22.0, 21.0), TireParams(60.0, 5.0)], ids=["default", "sedan-rear", "stiff-x"]
)
@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_force_stays_inside_the_friction_circle(model, tire):
    slip, alpha, fz, mu = dense_grid()
    fx, fy = model.forces(tire, slip, alpha, fz, mu)
    assert np.isfinite(fx).all() and np.isfinite(fy).all()
    excess = np.hypot(fx, fy) - mu * fz
    assert excess.max() <= 1e-9 * 10000.0, f"|F| exceeds mu Fz by {excess.max():.3g} N"


@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_sign_conventions(model):
    """Eq. 6 and 8: positive slip ratio (driving) pushes the tire forward, positive slip angle pushes it to the left."""
    slip, alpha, fz, mu = (g[..., 1:, 1:] for g in dense_grid())  # F_z > 0 and mu > 0
    fx, fy = model.forces(TIRE, slip, alpha, fz, mu)
    assert np.array_equal(np.sign(fx), np.sign(slip))
    assert np.array_equal(np.sign(fy), np.sign(alpha))


@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_lateral_force_is_odd_in_slip_angle(model):
    slip, alpha, fz, mu = dense_grid()
    fx_pos, fy_pos = model.forces(TIRE, slip, alpha, fz, mu)
    fx_neg, fy_neg = model.forces(TIRE, slip, -alpha, fz, mu)
    np.testing.assert_allclose(fy_neg, -fy_pos, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(fx_neg, fx_pos, rtol=1e-12, atol=1e-9)


# --- linear region: the slope at zero slip is the stiffness of TireParams -----------------------------------------


@pytest.mark.parametrize("tire", [TIRE, TireParams(22.0, 21.0)], ids=["default", "sedan-rear"])
@pytest.mark.parametrize("fz", [800.0, 5000.0, 9000.0])
@pytest.mark.parametrize("mu", [0.1, 0.5, 1.2])
@pytest.mark.parametrize("model", LINEAR_MODELS, ids=LINEAR_IDS)
def test_small_slip_slope_is_the_linear_stiffness(model, tire, fz, mu):
    h = 1e-5
    fx_plus, _ = model.forces(tire, h, 0.0, fz, mu)
    fx_minus, _ = model.forces(tire, -h, 0.0, fz, mu)
    _, fy_plus = model.forces(tire, 0.0, h, fz, mu)
    _, fy_minus = model.forces(tire, 0.0, -h, fz, mu)
    c_x = tire.longitudinal_stiffness_per_load * fz  # N per unit slip ratio
    c_y = tire.cornering_stiffness_per_load_per_rad * fz  # N/rad
    assert (fx_plus - fx_minus) / (2 * h) == pytest.approx(c_x, rel=1e-3)
    assert (fy_plus - fy_minus) / (2 * h) == pytest.approx(c_y, rel=1e-3)


def test_burckhardt_small_slip_slope_is_that_of_its_curve():
    """mu(s) = c1 (1 - exp(-c2 s)) - c3 s has slope c1 c2 - c3 at s = 0, scaled by mu / (curve peak)."""
    c1, c2, c3 = DRY_ASPHALT
    _, peak = closed_form_peak(c1, c2, c3)
    fz, mu, h = 4000.0, 0.7, 1e-6
    fx, _ = BurckhardtTire("dry_asphalt").forces(TIRE, h, 0.0, fz, mu)
    assert fx / h == pytest.approx(mu / peak * (c1 * c2 - c3) * fz, rel=1e-3)


# --- saturation: the force reaches mu F_z and no more ---------------------------------------------------------------


@pytest.mark.parametrize("mu", [0.1, 0.3, 0.8, 1.2])
@pytest.mark.parametrize("model", MODELS, ids=MODEL_IDS)
def test_peak_force_over_slip_is_mu_fz(model, mu):
    fz = 5000.0
    slip = np.linspace(-1.0, 1.0, 20001)
    alpha = np.linspace(-1.3, 1.3, 26001)
    fx, _ = model.forces(TIRE, slip, 0.0, fz, mu)
    _, fy = model.forces(TIRE, 0.0, alpha, fz, mu)
    assert np.abs(fx).max() == pytest.approx(mu * fz, rel=0.01)
    assert np.abs(fy).max() == pytest.approx(mu * fz, rel=0.01)


@pytest.mark.parametrize("mu", [0.1, 0.5, 0.9, 1.5])
def test_dugoff_saturates_to_mu_fz_at_large_slip(mu):
    """Saturated Dugoff force: |F| = mu F_z (1 - lambda / 2), lambda = mu F_z (1 + sigma) / (2 |C s|) -> 0 as the slip
    grows."""
    fz = 6000.0
    fx_locked, _ = DugoffTire().forces(TIRE, -1.0, 0.0, fz, mu)
    assert -fx_locked == pytest.approx(mu * fz, rel=1e-6)
    fx_spin, _ = DugoffTire().forces(TIRE, 1.0, 0.0, fz, mu)
    lam = mu * fz * 2.0 / (2.0 * 25.0 * fz)
    assert fx_spin == pytest.approx(mu * fz * (1.0 - lam / 2.0), rel=1e-9)
    _, fy_side = DugoffTire().forces(TIRE, 0.0, 1.3, fz, mu)
    lam = mu * fz / (2.0 * 16.0 * fz * math.tan(1.3))
    assert fy_side == pytest.approx(mu * fz * (1.0 - lam / 2.0), rel=1e-9)
    assert fy_side > 0.98 * mu * fz


@pytest.mark.parametrize("shape_c", [1.2, 1.4, 1.9])
def test_magic_formula_slides_at_sin_c_pi_over_2_of_the_peak(shape_c):
    """A locked wheel has an unbounded slip demand: x -> inf, atan x -> pi / 2, |F| -> D sin(C pi / 2)."""
    fz, mu = 5000.0, 0.8
    fx, _ = MagicFormulaTire(shape_c=shape_c).forces(TIRE, -1.0, 0.0, fz, mu)
    assert -fx == pytest.approx(mu * fz * math.sin(shape_c * math.pi / 2.0), rel=1e-6)


def test_magic_formula_peak_lies_at_the_closed_form_demand():
    """With E = 0 the peak is at C atan(x) = pi / 2, i.e. demand |F_lin| = C D tan(pi / (2 C))."""
    fz, mu, shape_c = 5000.0, 0.6, 1.4
    demand_n = shape_c * mu * fz * math.tan(math.pi / (2.0 * shape_c))
    slip_peak = demand_n / (25.0 * fz)  # F_lin = C_x sigma / (1 + sigma), solved for sigma > 0
    slip_peak = slip_peak / (1.0 - slip_peak)
    slip = np.linspace(0.0, 0.5, 50001)
    fx, _ = MagicFormulaTire(shape_c=shape_c).forces(TIRE, slip, 0.0, fz, mu)
    assert slip[np.argmax(fx)] == pytest.approx(slip_peak, abs=2e-5)
    assert fx.max() == pytest.approx(mu * fz, rel=1e-8)


# --- Burckhardt: the tabulated curves and their peaks ---------------------------------------------------------------


def test_burckhardt_table_holds_the_published_coefficients():
    assert SURFACES["dry_asphalt"] == DRY_ASPHALT
    assert SURFACES["wet_asphalt"] == WET_ASPHALT


def test_dry_asphalt_peak_is_the_closed_form():
    s_star, mu_star = closed_form_peak(*DRY_ASPHALT)
    assert s_star == pytest.approx(0.170, abs=0.001)  # Kiencke & Nielsen: dry asphalt peaks at about 17 % slip
    assert mu_star == pytest.approx(1.17, abs=0.005)  # ... at mu about 1.17
    assert peak_slip(*DRY_ASPHALT) == pytest.approx(s_star, rel=1e-12)
    assert peak_mu(*DRY_ASPHALT) == pytest.approx(mu_star, rel=1e-12)


@pytest.mark.parametrize("surface", sorted(SURFACES))
def test_peak_mu_is_the_maximum_of_each_curve(surface):
    c1, c2, c3 = SURFACES[surface]
    s = np.linspace(0.0, 1.0, 100001)
    curve = c1 * (1.0 - np.exp(-c2 * s)) - c3 * s
    assert peak_mu(c1, c2, c3) == pytest.approx(curve.max(), rel=1e-8)
    if c3 > 0.0:  # with c3 = 0 (ice) the curve rises monotonically: its maximum is at s = 1, flat to rounding
        assert peak_slip(c1, c2, c3) == pytest.approx(s[np.argmax(curve)], abs=2e-5)
    else:
        assert peak_slip(c1, c2, c3) == 1.0


def test_burckhardt_tire_on_its_own_peak_reproduces_the_curve():
    """On a road whose mu is the surface's peak the scaling is 1: F_x / F_z is the tabulated curve, maximal at s*."""
    s_star, mu_star = closed_form_peak(*DRY_ASPHALT)
    fz = 4000.0
    slip = np.linspace(0.0, 1.0, 100001)
    fx, fy = BurckhardtTire("dry_asphalt").forces(TIRE, slip, 0.0, fz, mu_star)
    expected = np.array([burckhardt_curve(*DRY_ASPHALT, s) for s in slip[::1000]])
    np.testing.assert_allclose(fx[::1000] / fz, expected, rtol=1e-9, atol=1e-12)
    assert np.all(fy == 0.0)
    assert slip[np.argmax(fx)] == pytest.approx(s_star, abs=2e-5)
    assert fx.max() == pytest.approx(mu_star * fz, rel=1e-8)
    # braking mirrors driving
    fx_brake, _ = BurckhardtTire("dry_asphalt").forces(TIRE, -slip, 0.0, fz, mu_star)
    np.testing.assert_allclose(fx_brake, -fx, rtol=1e-12)


def test_wet_to_dry_asphalt_peak_ratio_is_about_0_68():
    """The ratio the paper's Table 7 compares with (dry-road estimate vs wet sideway-force wheel, 0.68-0.70)."""
    _, dry = closed_form_peak(*DRY_ASPHALT)
    _, wet = closed_form_peak(*WET_ASPHALT)
    assert wet / dry == pytest.approx(0.68, abs=0.01)
    assert peak_mu(*SURFACES["wet_asphalt"]) / peak_mu(*SURFACES["dry_asphalt"]) == pytest.approx(wet / dry, rel=1e-12)


def test_burckhardt_picks_the_surface_whose_peak_is_nearest_the_road_mu():
    """On a road of mu 0.80 (wet asphalt's peak) the curve has wet asphalt's shape: it peaks at wet asphalt's s*."""
    s_wet, mu_wet = closed_form_peak(*WET_ASPHALT)
    s_dry, _ = closed_form_peak(*DRY_ASPHALT)
    slip = np.linspace(0.0, 1.0, 100001)
    fx, _ = BurckhardtTire().forces(TIRE, slip, 0.0, 5000.0, mu_wet)
    assert slip[np.argmax(fx)] == pytest.approx(s_wet, abs=2e-5)
    assert abs(s_wet - s_dry) > 0.03
    # a fixed surface keeps its own shape whatever the road
    fx, _ = BurckhardtTire("dry_asphalt").forces(TIRE, slip, 0.0, 5000.0, mu_wet)
    assert slip[np.argmax(fx)] == pytest.approx(s_dry, abs=2e-5)
    assert fx.max() == pytest.approx(mu_wet * 5000.0, rel=1e-8)


def test_burckhardt_combined_slip_uses_the_resultant_slip():
    """s_y = tan(alpha) C_y / C_x, s = |(s_x, s_y)|; the force has the curve's magnitude at s, along (s_x, s_y)."""
    c1, c2, c3 = DRY_ASPHALT
    _, mu_star = closed_form_peak(c1, c2, c3)
    sigma, alpha, fz = 0.06, 0.08, 3000.0
    s_x, s_y = sigma, math.tan(alpha) * 16.0 / 25.0
    s = math.hypot(s_x, s_y)
    fx, fy = BurckhardtTire("dry_asphalt").forces(TIRE, sigma, alpha, fz, mu_star)
    magnitude = burckhardt_curve(c1, c2, c3, s) * fz
    assert fx == pytest.approx(magnitude * s_x / s, rel=1e-12)
    assert fy == pytest.approx(magnitude * s_y / s, rel=1e-12)


# --- Dugoff: our equation 7 against Dugoff's original and against the paper's print --------------------------------


def dugoff_original(tire, sigma, alpha, fz, mu):
    """Dugoff, Fancher and Segel (1970), written out independently of the package (numpy, no clamp below 1.3 rad)."""
    cx = tire.longitudinal_stiffness_per_load * fz
    cy = tire.cornering_stiffness_per_load_per_rad * fz
    q = np.maximum(1.0 + sigma, 1e-9)
    demand = np.hypot(cx * sigma, cy * np.tan(alpha))
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = mu * fz * q / (2.0 * demand)
        f = np.where(lam >= 1.0, 1.0, (2.0 - lam) * lam)
        fx = np.where(demand > 0, cx * sigma / q * f, 0.0)
        fy = np.where(demand > 0, cy * np.tan(alpha) / q * f, 0.0)
    return fx, fy


def dugoff_as_printed(tire, sigma, alpha, fz, mu):
    """The paper's eq. 7 as printed, without the factor 2: lambda = mu F_z (1 + s) / sqrt((C_x s)^2 + (C_y tan a)^2)."""
    cx = tire.longitudinal_stiffness_per_load * fz
    cy = tire.cornering_stiffness_per_load_per_rad * fz
    q = np.maximum(1.0 + sigma, 1e-9)
    demand = np.hypot(cx * sigma, cy * np.tan(alpha))
    with np.errstate(divide="ignore", invalid="ignore"):
        lam = mu * fz * q / demand
        f = np.where(lam >= 1.0, 1.0, (2.0 - lam) * lam)
        fx = np.where(demand > 0, cx * sigma / q * f, 0.0)
        fy = np.where(demand > 0, cy * np.tan(alpha) / q * f, 0.0)
    return fx, fy


def test_dugoff_matches_the_original_formula():
    slip, alpha, fz, mu = dense_grid()
    fx, fy = DugoffTire().forces(TIRE, slip, alpha, fz, mu)
    fx_ref, fy_ref = dugoff_original(TIRE, slip, alpha, fz, mu)
    np.testing.assert_allclose(fx, fx_ref, rtol=1e-9, atol=1e-6)
    np.testing.assert_allclose(fy, fy_ref, rtol=1e-9, atol=1e-6)


def test_paper_printed_eq7_exceeds_mu_fz_and_ours_does_not():
    """Without the 2 the saturated force is mu F_z (2 - lambda), up to 2 mu F_z: the print breaks the friction limit."""
    slip, alpha, fz, mu = (g[..., 1:, 1:] for g in dense_grid())
    fx_p, fy_p = dugoff_as_printed(TIRE, slip, alpha, fz, mu)
    fx, fy = DugoffTire().forces(TIRE, slip, alpha, fz, mu)
    printed_ratio = np.hypot(fx_p, fy_p) / (mu * fz)
    ours_ratio = np.hypot(fx, fy) / (mu * fz)
    assert printed_ratio.max() > 1.9
    assert ours_ratio.max() <= 1.0 + 1e-12
    # a single braking point, by hand: sigma = -0.2, F_z = 5 kN, mu = 0.5
    # printed: lambda = 0.5 * 5000 * 0.8 / (25 * 5000 * 0.2) = 0.08,
    # |F| = 25000 / 0.8 * (2 - 0.08) * 0.08 = 4800 N > mu F_z = 2500 N
    fx_p, _ = dugoff_as_printed(TIRE, -0.2, 0.0, 5000.0, 0.5)
    assert -fx_p == pytest.approx(4800.0, rel=1e-12)
    # ours: lambda = 0.04, |F| = mu F_z (1 - lambda / 2) = 2450 N
    fx, _ = DugoffTire().forces(TIRE, -0.2, 0.0, 5000.0, 0.5)
    assert -fx == pytest.approx(2450.0, rel=1e-12)


# --- construction ---------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "field", "shown"),
    [
        ({"shape_c": 2.5}, "shape_c", "2.5"),
        ({"shape_c": 1.0}, "shape_c", "1.0"),
        ({"shape_c": 0.5}, "shape_c", "0.5"),
        ({"curvature_e": 1.5}, "curvature_e", "1.5"),
        ({"shape_c": float("nan")}, "shape_c", "nan"),
    ],
)
def test_invalid_magic_formula_shape_raises(kwargs, field, shown):
    with pytest.raises(ValueError) as excinfo:
        MagicFormulaTire(**kwargs)
    assert field in str(excinfo.value)
    assert shown in str(excinfo.value)


def test_unknown_burckhardt_surface_raises():
    with pytest.raises(ValueError, match="surface.*'gravel'"):
        BurckhardtTire("gravel")


def test_models_by_name():
    assert set(TIRE_MODELS) == {"dugoff", "magic-formula", "burckhardt"}
    assert tire_model_by_name("magic-formula", shape_c=1.6) == MagicFormulaTire(shape_c=1.6)
    assert tire_model_by_name("burckhardt", surface="snow") == BurckhardtTire("snow")
    with pytest.raises(ValueError, match="'pacejka'"):
        tire_model_by_name("pacejka")
