"""A tire's stiffness_scale moves the slope at zero slip by its factor for every model, and leaves the peak at mu F_z."""

import numpy as np
import pytest

from roadgrip.vehicle.params import TireParams
from roadgrip.vehicle.tires import BurckhardtTire, DugoffTire, MagicFormulaTire

TIRE = TireParams(25.0, 16.0)
FZ_N = 4000.0
MODELS = (DugoffTire, MagicFormulaTire, BurckhardtTire)


def slopes(model, mu=0.8, step=1e-5):
    """(d fx / d sigma, d fy / d alpha) at zero slip, by a small forward step."""
    fx, _ = model.forces(TIRE, step, 0.0, FZ_N, mu)
    _, fy = model.forces(TIRE, 0.0, step, FZ_N, mu)
    return fx.item() / step, fy.item() / step


@pytest.mark.parametrize("cls", MODELS, ids=lambda c: c.name)
@pytest.mark.parametrize("scale", (0.7, 1.3))
def test_stiffness_scale_moves_the_initial_slope_by_its_factor(cls, scale):
    base, scaled = slopes(cls()), slopes(cls(stiffness_scale=scale))
    assert scaled[0] == pytest.approx(scale * base[0], rel=1e-3)
    assert scaled[1] == pytest.approx(scale * base[1], rel=1e-3)


@pytest.mark.parametrize("cls", MODELS, ids=lambda c: c.name)
@pytest.mark.parametrize("mu", (0.2, 0.5, 0.9))
def test_stiffness_scale_keeps_the_peak_at_mu_fz(cls, mu):
    slip = np.linspace(-1.0, 1.0, 4001)
    for scale in (0.7, 1.0, 1.3):
        fx, _ = cls(stiffness_scale=scale).forces(TIRE, slip, 0.0, FZ_N, mu)
        assert np.abs(fx).max() <= mu * FZ_N * (1 + 1e-9)
        assert np.abs(fx).max() == pytest.approx(mu * FZ_N, rel=0.03 if cls is DugoffTire else 1e-3)


def test_default_scale_is_one_and_bad_scales_are_refused():
    assert all(cls().stiffness_scale == 1.0 for cls in MODELS)
    with pytest.raises(ValueError, match=r"DugoffTire.stiffness_scale must be in \[0.3, 3.0\], got 5"):
        DugoffTire(stiffness_scale=5)
