from pathlib import Path

import numpy as np
import pytest

from roadgrip.sim.integrator import CHANNELS
from roadgrip.sim.scenario_file import load_scenarios, scenario_from_dict
from roadgrip.sim.simulate import simulate_truth
from roadgrip.vehicle.params import MIDSIZE_SEDAN
from roadgrip.vehicle.tires import MagicFormulaTire

EXAMPLE = Path(__file__).parents[2] / "examples" / "wet_patch_braking.yaml"
CH = {name: k for k, name in enumerate(CHANNELS)}
RUN = {
    "run_id": "r1",
    "road": {"kind": "circle", "radius_m": 200.0, "arc_length_m": 900.0},
    "mu": {"stations_m": [0, 100], "mu_left": [0.9, 0.4], "mode": "linear"},
    "speed": {"times_s": [0, 10], "speeds_mps": [5, 15]},
    "vehicle": "midsize-sedan",
    "tire": {"model": "magic-formula", "shape_c": 1.5},
    "duration_s": 10,
}


def test_a_run_is_built_from_its_mapping():
    s = scenario_from_dict(RUN)
    assert s.vehicle == MIDSIZE_SEDAN and s.tire == MagicFormulaTire(shape_c=1.5)
    assert s.path.length_m == pytest.approx(900.0, rel=1e-3) and s.road == "circle"
    assert s.mu.at([50.0]) == pytest.approx([0.65]) and s.n_samples == 100


def test_grade_and_production_effects_are_read():
    from roadgrip.sim.production import ProductionEffects

    s = scenario_from_dict(RUN)
    assert s.grade.is_flat and s.effects == ProductionEffects.off()
    s = scenario_from_dict(RUN | {"grade": {"stations_m": [0, 100], "grade_rad": [0.0, 0.04]}, "effects": "production"})
    assert s.grade.at(50.0) == pytest.approx(0.02) and s.effects == ProductionEffects.production()
    s = scenario_from_dict(RUN | {"grade": -0.02, "effects": {"speed_from_wheels": True}})
    assert s.grade.at(10.0) == pytest.approx(-0.02) and s.effects == ProductionEffects(speed_from_wheels=True)


def test_the_example_file_loads():
    scenarios = load_scenarios(EXAMPLE)
    assert [s.run_id for s in scenarios] == ["wet-patch-braking-suv", "split-mu-braking-sedan"]


@pytest.mark.parametrize(
    "change, message",
    [
        ({"colour": "red"}, r"run 'r1': unknown key\(s\) \['colour'\]"),
        ({"road": {"kind": "circle", "radius_m": -5.0, "arc_length_m": 100.0}}, "radius_m must be > 0, got -5.0"),
        ({"road": {"kind": "spiral"}}, "road.kind must be one of .* got 'spiral'"),
        ({"mu": 1.7}, r"mu_left must lie in \[0, 1.5\], got 1.7"),
        ({"mu": {"stations_m": [0], "mu_left": [0.5], "slope": 1}}, r"unknown key\(s\) \['slope'\]"),
        ({"vehicle": {"mass_kg": -10.0}}, "mass_kg must be in .* got -10.0"),
        ({"vehicle": {"mass": 1500.0}}, r"unknown VehicleParams key\(s\) \['mass'\]"),
        ({"speed": {"times_s": [0, 10]}}, r"missing key\(s\) \['speeds_mps'\]"),
        ({"grade": 0.5}, r"grade_rad must lie in \[-0.3, 0.3\], got 0.5"),
        ({"effects": "some"}, "effects must be 'off', 'production' or a mapping"),
        ({"effects": {"radius_spread": 0.01}}, r"unknown ProductionEffects key\(s\) \['radius_spread'\]"),
    ],
)
def test_bad_runs_name_the_key_and_value(change, message):
    with pytest.raises((ValueError, TypeError), match=message):
        scenario_from_dict(RUN | change)


def test_split_mu_braking_stays_straight():
    """ABS with select-low at the rear and a yaw-moment build-up delay at the front keeps the car on a 0.9 / 0.2 split."""
    split = load_scenarios(EXAMPLE)[1]
    out = simulate_truth([split])[0]
    braking = out[:, CH["t_s"]] > 5.0
    assert out[braking, CH["abs_active"]].any()
    assert np.abs(out[:, CH["yaw_rate_radps"]]).max() < 0.15
    assert np.abs(out[:, CH["y_m"]]).max() < 2.0
    assert out[-1, CH["vx_mps"]] < 0.5, "the car stops"
