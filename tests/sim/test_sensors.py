import numpy as np
import pytest

from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.sensors import HEBEI_ORIGIN, SensorModel
from roadgrip.sim.simulate import simulate
from roadgrip.units import G_MPS2


@pytest.fixture(scope="module")
def run_pair():
    scenario = [s for s in paper_scenarios() if s.run_id == "paper-high-circular-e1"]
    return simulate(scenario, SensorModel.noiseless()), simulate(scenario)


def test_noiseless_sensors_report_the_truth(run_pair):
    clean, _ = run_pair
    assert np.allclose(clean["speed_mps"].to_numpy(), clean["vx_true_mps"].to_numpy())
    assert np.allclose(clean["yaw_rate_radps"].to_numpy(), clean["yaw_rate_true_radps"].to_numpy())
    assert np.allclose(clean["steering_wheel_angle_rad"].to_numpy(), 16.0 * clean["steer_true_rad"].to_numpy())
    expected_lat = clean["ay_true_mps2"].to_numpy() + G_MPS2 * np.sin(clean["roll_true_rad"].to_numpy())
    assert np.allclose(clean["accel_lat_mps2"].to_numpy(), expected_lat), "a rolled IMU reads a_y + g sin(roll)"


def test_noise_has_the_documented_size(run_pair):
    clean, noisy = run_pair
    model = SensorModel()
    wheel_err = noisy["wheel_speed_fl_radps"].to_numpy() - clean["wheel_speed_fl_radps"].to_numpy()
    assert wheel_err.std() == pytest.approx(model.wheel_speed_noise_radps, rel=0.15)
    yaw_err = noisy["yaw_rate_radps"].to_numpy() - clean["yaw_rate_radps"].to_numpy()
    assert (yaw_err - yaw_err.mean()).std() == pytest.approx(model.yaw_rate_noise_radps, rel=0.15)


def test_gnss_starts_at_the_hebei_origin_and_follows_the_road(run_pair):
    clean, noisy = run_pair
    lat, lon = clean["latitude_deg"].to_numpy(), clean["longitude_deg"].to_numpy()
    assert (lat[0], lon[0]) == pytest.approx(HEBEI_ORIGIN, abs=1e-9)
    east_m = (lon - lon[0]) * np.pi / 180 * 6378137.0 * np.cos(np.radians(lat[0]))
    assert east_m == pytest.approx(clean["x_m"].to_numpy(), abs=0.5 + 1e-3 * np.abs(east_m).max())
    err_north_m = (noisy["latitude_deg"].to_numpy() - lat) * np.pi / 180 * 6.36e6
    assert 0.2 < np.abs(err_north_m).mean() < 6.0


def test_sensor_model_rejects_bad_values():
    with pytest.raises(ValueError, match=r"SensorModel.gnss_noise_m must be in \[0.0, 100.0\], got -1"):
        SensorModel(gnss_noise_m=-1)
    with pytest.raises(TypeError, match="unexpected keyword"):
        SensorModel(gps_noise=1.0)
