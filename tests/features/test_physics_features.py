import numpy as np
import pyarrow.compute as pc
import pytest

from roadgrip.features.windows import feature_columns, feature_matrix
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.sensors import SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import PAPER_SUV


def test_physics_features_are_the_slips_and_accelerations_in_g():
    run = [s for s in paper_scenarios() if s.run_id == "paper-low-straight-e1"]
    table = simulate(run, SensorModel.noiseless())
    table = table.filter(pc.greater(table["vx_true_mps"], 5.0))
    x = feature_matrix(table, "physics", PAPER_SUV.wheel_radius_m, PAPER_SUV.steering_ratio)
    names = feature_columns("physics")
    col = {n: x[:, k] for k, n in enumerate(names)}
    for w in ("fl", "rr"):  # straight road: hub speed = CoG speed, so the slips are the simulator's own
        assert col[f"slip_ratio_{w}"] == pytest.approx(table[f"slip_ratio_{w}"].to_numpy(), abs=2e-3)
    assert col["accel_lon_g"] == pytest.approx(table["ax_true_mps2"].to_numpy() / G_MPS2, abs=1e-5)


def test_the_physics_set_needs_the_vehicle_profile():
    table = simulate(paper_scenarios()[:1])
    with pytest.raises(ValueError, match="needs the vehicle profile"):
        feature_matrix(table, "physics")
    assert np.isfinite(feature_matrix(table, "physics", 0.383, 16.0)).all()
