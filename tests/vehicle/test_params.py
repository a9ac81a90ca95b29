"""Vehicle and tire parameters: defaults, input validation, YAML round trip and the static axle loads."""

import dataclasses
import math

import pytest

from roadgrip.units import G_MPS2
from roadgrip.vehicle.params import MIDSIZE_SEDAN, PAPER_SUV, VEHICLES, TireParams, VehicleParams, vehicle_by_name

SHIPPED = [PAPER_SUV, MIDSIZE_SEDAN]
SHIPPED_IDS = [v.name for v in SHIPPED]


# --- defaults -------------------------------------------------------------------------------------------------------


def test_defaults_construct_and_are_the_paper_suv():
    assert VehicleParams() == PAPER_SUV
    assert TireParams() == TireParams(25.0, 16.0)


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_shipped_vehicles_are_consistent(vehicle):
    # re-running the validation on a copy raises nothing
    assert VehicleParams(**{f: getattr(vehicle, f) for f in vehicle.__dataclass_fields__}) == vehicle
    assert 0.0 < vehicle.cg_to_front_axle_m < vehicle.wheelbase_m
    assert math.isclose(vehicle.cg_to_front_axle_m + vehicle.cg_to_rear_axle_m, vehicle.wheelbase_m)
    assert 0.0 < vehicle.sprung_mass_kg < vehicle.mass_kg
    assert vehicle.frontal_area_m2 > 0.0
    assert math.isclose(sum(vehicle.drive_split), 1.0)
    assert vehicle_by_name(vehicle.name) is vehicle
    assert VEHICLES[vehicle.name] is vehicle


@pytest.mark.parametrize(("drive", "split"), [("fwd", (1.0, 0.0)), ("rwd", (0.0, 1.0)), ("awd", (0.4, 0.6))])
def test_drive_split_follows_the_layout(drive, split):
    assert PAPER_SUV.replace(drive=drive, front_drive_share=0.4).drive_split == pytest.approx(split)


# --- invalid input: the error names the field and the value --------------------------------------------------------


@pytest.mark.parametrize(
    ("changes", "field", "shown"),
    [
        ({"mass_kg": -1500.0}, "mass_kg", "-1500.0"),
        ({"mass_kg": 0.0}, "mass_kg", "0.0"),
        ({"wheel_radius_m": 0.0}, "wheel_radius_m", "0.0"),
        ({"wheel_radius_m": -0.3}, "wheel_radius_m", "-0.3"),
        ({"wheelbase_m": float("nan")}, "wheelbase_m", "nan"),
        ({"cg_height_m": float("inf")}, "cg_height_m", "inf"),
        ({"cg_to_front_axle_m": 3.008}, "cg_to_front_axle_m", "3.008"),  # CoG on the rear axle
        ({"cg_to_front_axle_m": 3.5}, "cg_to_front_axle_m", "3.5"),  # CoG behind the rear axle
        ({"drive": "4wd"}, "drive", "'4wd'"),
        ({"drive": "AWD"}, "drive", "'AWD'"),
        ({"unsprung_mass_kg": 2400.0}, "unsprung_mass_kg", "2400.0"),
        ({"yaw_inertia_kgm2": 0.0}, "yaw_inertia_kgm2", "0.0"),
    ],
)
def test_invalid_values_raise_value_error_naming_field_and_value(changes, field, shown):
    with pytest.raises(ValueError) as excinfo:
        PAPER_SUV.replace(**changes)
    message = str(excinfo.value)
    assert field in message
    assert shown in message


@pytest.mark.parametrize(("field", "value"), [("mass_kg", "heavy"), ("wheel_radius_m", None), ("steering_ratio", True)])
def test_non_numeric_values_raise_type_error_naming_field_and_value(field, value):
    with pytest.raises(TypeError) as excinfo:
        PAPER_SUV.replace(**{field: value})
    assert field in str(excinfo.value)
    assert repr(value) in str(excinfo.value)


@pytest.mark.parametrize(
    ("changes", "field", "shown"),
    [
        ({"longitudinal_stiffness_per_load": -25.0}, "longitudinal_stiffness_per_load", "-25.0"),
        ({"cornering_stiffness_per_load_per_rad": 0.0}, "cornering_stiffness_per_load_per_rad", "0.0"),
    ],
)
def test_invalid_tire_params_raise_naming_field_and_value(changes, field, shown):
    with pytest.raises(ValueError) as excinfo:
        TireParams(**changes)
    assert field in str(excinfo.value)
    assert shown in str(excinfo.value)


def test_from_dict_rejects_unknown_keys_naming_them():
    data = PAPER_SUV.to_dict()
    data["masss_kg"] = 2000.0
    with pytest.raises(ValueError) as excinfo:
        VehicleParams.from_dict(data)
    assert "masss_kg" in str(excinfo.value)


def test_from_dict_rejects_unknown_nested_tire_keys_naming_them():
    data = PAPER_SUV.to_dict()
    data["tire_rear"]["grip"] = 1.0
    with pytest.raises(ValueError) as excinfo:
        VehicleParams.from_dict(data)
    assert "grip" in str(excinfo.value)


def test_from_dict_rejects_a_non_mapping():
    with pytest.raises(TypeError, match="list"):
        VehicleParams.from_dict([("mass_kg", 1500.0)])


def test_from_dict_validates_values():
    with pytest.raises(ValueError, match="mass_kg.*-5"):
        VehicleParams.from_dict({"mass_kg": -5.0})


def test_vehicle_by_name_rejects_unknown_names():
    with pytest.raises(ValueError, match="'tractor'"):
        vehicle_by_name("tractor")


# --- serialisation --------------------------------------------------------------------------------------------------


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_yaml_round_trip(vehicle, tmp_path):
    path = tmp_path / f"{vehicle.name}.yaml"
    vehicle.to_yaml(path)
    loaded = VehicleParams.from_yaml(path)
    assert loaded == vehicle
    assert isinstance(loaded.tire_front, TireParams) and isinstance(loaded.tire_rear, TireParams)


@pytest.mark.parametrize("vehicle", SHIPPED, ids=SHIPPED_IDS)
def test_dict_round_trip(vehicle):
    assert VehicleParams.from_dict(vehicle.to_dict()) == vehicle


def test_partial_dict_takes_defaults_for_missing_fields():
    v = VehicleParams.from_dict(
        {"name": "light", "mass_kg": 1200.0, "tire_front": {"longitudinal_stiffness_per_load": 20.0}}
    )
    assert v.mass_kg == 1200.0
    assert v.wheelbase_m == PAPER_SUV.wheelbase_m
    assert v.tire_front == TireParams(20.0, TireParams().cornering_stiffness_per_load_per_rad)


# --- static axle loads ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "vehicle",
    SHIPPED + [PAPER_SUV.replace(cg_to_front_axle_m=0.3), PAPER_SUV.replace(cg_to_front_axle_m=2.9, mass_kg=900.0)],
    ids=SHIPPED_IDS + ["cg-forward", "cg-rearward"],
)
def test_static_axle_loads_balance_weight_and_moment(vehicle):
    front_n, rear_n = vehicle.static_axle_loads_n
    weight_n = vehicle.mass_kg * G_MPS2
    # vertical force balance: the axles carry the weight
    assert front_n + rear_n == pytest.approx(weight_n, rel=1e-12)
    # moment balance about the CoG: front load x l_f = rear load x l_r
    assert front_n * vehicle.cg_to_front_axle_m == pytest.approx(rear_n * vehicle.cg_to_rear_axle_m, rel=1e-12)
    assert front_n > 0.0 and rear_n > 0.0


def test_static_axle_loads_of_the_paper_suv():
    # l_r / L = (3.008 - 1.444) / 3.008 of 2335 kg on the front axle
    front_n, rear_n = PAPER_SUV.static_axle_loads_n
    assert front_n == pytest.approx(2335.0 * 9.80665 * 1.564 / 3.008, rel=1e-9)
    assert rear_n == pytest.approx(2335.0 * 9.80665 * 1.444 / 3.008, rel=1e-9)


def test_params_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        PAPER_SUV.mass_kg = 1.0
