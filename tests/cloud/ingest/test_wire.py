import dataclasses
import json
import math

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from roadgrip.cloud.ingest.wire import VSS, PayloadError, SampleError, parse_payload
from roadgrip.data.schema import CHANNEL_NAMES, TELEMETRY, TELEMETRY_COLUMNS
from roadgrip.data.telemetry import RANGES, VEHICLE_ID_RE
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import DEFAULT_START_EPOCH_MS, simulate

NOW_MS = DEFAULT_START_EPOCH_MS + 100_000
DROP = object()  # a key to leave out of a sample
JSON_TYPE = "application/json"
NDJSON_TYPE = "application/x-ndjson"

SAMPLE = {
    "vehicle_id": "car-1",
    "timestamp_ms": NOW_MS - 1_000,
    "latitude_deg": 38.04,
    "longitude_deg": 114.51,
    "speed_mps": 20.0,
    "accel_lon_mps2": 0.5,
    "accel_lat_mps2": -0.2,
    "yaw_rate_radps": 0.01,
    "steering_wheel_angle_rad": 0.1,
    "wheel_speed_fl_radps": 57.1,
    "wheel_speed_fr_radps": 57.2,
    "wheel_speed_rl_radps": 57.0,
    "wheel_speed_rr_radps": 57.3,
    "abs_active": False,
    "acc_active": True,
    "lateral_speed_mps": 0.05,
}


def sample(**changes) -> dict:
    """A valid wire sample with some fields changed (DROP: left out)."""
    out = {**SAMPLE, **changes}
    return {k: v for k, v in out.items() if v is not DROP}


def body_of(samples, fmt: str = "json") -> bytes:
    if fmt == "ndjson":
        return "".join(json.dumps(s) + "\n" for s in samples).encode()
    return json.dumps(samples).encode()


def parse(samples, fmt: str = "json", **options):
    content_type = {"json": JSON_TYPE, "ndjson": NDJSON_TYPE}[fmt]
    return parse_payload(body_of(samples, fmt), content_type=content_type, **{"now_ms": NOW_MS, **options})


def only_error(one, **options) -> SampleError:
    samples, errors = parse([one], **options)
    assert samples == [] and len(errors) == 1, (samples, errors)
    assert errors[0].index == 0
    return errors[0]


# ------------------------------------------------------------------------------------------------ valid samples


@pytest.fixture(scope="module")
def simulated() -> list[dict]:
    run = dataclasses.replace(paper_scenarios()[0], duration_s=3.0)
    return simulate([run]).select(list(TELEMETRY_COLUMNS)).to_pylist()


@pytest.mark.parametrize("fmt", ["json", "ndjson"])
def test_simulated_samples_round_trip_in_order_with_exactly_the_wire_names(simulated, fmt):
    samples, errors = parse(simulated, fmt, now_ms=simulated[-1]["timestamp_ms"])
    assert errors == []
    assert samples == simulated
    for s in samples:
        assert list(s) == list(TELEMETRY_COLUMNS)
        assert type(s["timestamp_ms"]) is int and type(s["abs_active"]) is bool and type(s["speed_mps"]) is float


def test_integers_become_floats_and_absent_or_null_optional_fields_become_none():
    samples, errors = parse([sample(speed_mps=20, latitude_deg=DROP, longitude_deg=None, lateral_speed_mps=DROP)])
    assert errors == []
    (s,) = samples
    assert list(s) == list(TELEMETRY_COLUMNS)
    assert s["speed_mps"] == 20.0 and type(s["speed_mps"]) is float
    assert s["latitude_deg"] is None and s["longitude_deg"] is None and s["lateral_speed_mps"] is None


@pytest.mark.parametrize("text", ["1.7672256e12", "1767225600000.0"])
def test_an_integral_float_timestamp_is_accepted_as_an_integer(text):
    body = json.dumps(sample(timestamp_ms=1_767_225_600_000)).replace("1767225600000", text).encode()
    assert text in body.decode()
    samples, errors = parse_payload(body, content_type=JSON_TYPE, now_ms=NOW_MS)
    assert errors == [] and samples[0]["timestamp_ms"] == 1_767_225_600_000
    assert type(samples[0]["timestamp_ms"]) is int


def test_duplicates_inside_a_payload_are_kept():
    samples, errors = parse([sample(), sample(), sample()])
    assert errors == [] and len(samples) == 3


# ---------------------------------------------------------------------------------------------------- bad values

TS_RULE = "timestamp_ms must be an integer number of milliseconds since the Unix epoch"
BAD_VALUES = [
    ("speed_mps", "12", 'speed_mps must be a number, got string "12"'),
    ("speed_mps", True, "speed_mps must be a number, got boolean true"),
    ("speed_mps", None, "speed_mps must be a number, got null"),
    ("speed_mps", [1, 2], "speed_mps must be a number, got array [1, 2]"),
    ("speed_mps", {"v": 1}, 'speed_mps must be a number, got object {"v": 1}'),
    ("latitude_deg", "38.1", 'latitude_deg must be a number, got string "38.1"'),
    ("speed_mps", math.nan, "speed_mps must be finite, got NaN"),
    ("yaw_rate_radps", math.inf, "yaw_rate_radps must be finite, got Infinity"),
    ("lateral_speed_mps", -math.inf, "lateral_speed_mps must be finite, got -Infinity"),
    ("speed_mps", 512, "speed_mps 512 outside [-5, 100] m/s"),
    ("speed_mps", -5.5, "speed_mps -5.5 outside [-5, 100] m/s"),
    ("abs_active", "yes", 'abs_active must be true or false, got string "yes"'),
    ("acc_active", 1, "acc_active must be true or false, got number 1"),
    ("acc_active", None, "acc_active must be true or false, got null"),
    ("vehicle_id", 42, "vehicle_id must be a string, got number 42"),
    ("vehicle_id", "bad id!", 'vehicle_id "bad id!" must be 1-64 characters of A-Za-z0-9_.-'),
    ("vehicle_id", "", 'vehicle_id "" must be 1-64'),
    ("vehicle_id", "x" * 65, 'vehicle_id "xxxxxxxxx'),
    ("vehicle_id", "car-1\n", 'vehicle_id "car-1\\n" must be 1-64'),
    ("timestamp_ms", str(NOW_MS), f'{TS_RULE}, got string "{NOW_MS}"'),
    ("timestamp_ms", True, f"{TS_RULE}, got boolean true"),
    ("timestamp_ms", NOW_MS - 0.5, f"timestamp_ms {NOW_MS - 0.5!r} is not a whole number of milliseconds"),
    ("timestamp_ms", -1, "timestamp_ms -1 must be >= 0"),
    ("timestamp_ms", math.nan, f"{TS_RULE}, got number NaN"),
]


@pytest.mark.parametrize("field, value, reason", BAD_VALUES, ids=[f"{f}={v!r}"[:40] for f, v, _ in BAD_VALUES])
def test_a_bad_value_is_refused_naming_the_field_the_value_and_the_rule(field, value, reason):
    error = only_error(sample(**{field: value}))
    assert error.field == field
    assert reason in error.reason


OUTSIDE = [
    (name, bound, value)
    for name, (low, high) in RANGES.items()
    for bound, value in (("low", low - 0.01 * (high - low)), ("high", high + 0.01 * (high - low)))
]


@pytest.mark.parametrize("name, bound, value", OUTSIDE, ids=[f"{n}-{b}" for n, b, _ in OUTSIDE])
def test_every_physical_range_refuses_a_value_just_outside_it(name, bound, value):
    low, high = RANGES[name]
    unit = next(c.unit for c in TELEMETRY if c.name == name)
    error = only_error(sample(**{name: value}))
    assert error.field == name
    assert error.reason == f"{name} {value!r} outside [{low:g}, {high:g}] {unit}"
    samples, errors = parse([sample(**{name: low}), sample(**{name: high})])  # the bounds themselves are valid
    assert errors == [] and len(samples) == 2


def test_nan_and_infinity_literals_in_the_body_are_refused():
    body = json.dumps([sample()] * 3).encode()
    body = body.replace(b'"speed_mps": 20.0', b'"speed_mps": NaN', 1)
    body = body.replace(b'"speed_mps": 20.0', b'"speed_mps": -Infinity', 1)
    samples, errors = parse_payload(body, content_type=JSON_TYPE, now_ms=NOW_MS)
    assert len(samples) == 1
    assert [(e.index, e.reason) for e in errors] == [
        (0, "speed_mps must be finite, got NaN"),
        (1, "speed_mps must be finite, got -Infinity"),
    ]


def test_a_huge_integer_is_out_of_range_not_a_crash():
    body = json.dumps([sample()]).replace("20.0", "9" * 4000).encode()
    samples, errors = parse_payload(body, content_type=JSON_TYPE, now_ms=NOW_MS)
    assert samples == [] and errors[0].field == "speed_mps" and "outside [-5, 100] m/s" in errors[0].reason


# ------------------------------------------------------------------------------------------------ keys


@pytest.mark.parametrize(
    "key, reason",
    [
        ("sped_mps", "unknown field 'sped_mps' (did you mean 'speed_mps'?)"),
        ("wheel_speed_fl_rps", "unknown field 'wheel_speed_fl_rps' (did you mean 'wheel_speed_fl_radps'?)"),
        ("colour", "unknown field 'colour'"),
        ("t_s", "unknown field 't_s': the wire format takes timestamp_ms"),
    ],
)
def test_an_unknown_field_is_refused_with_the_close_wire_name(key, reason):
    error = only_error(sample(**{key: 1.0}))
    assert error.field == key
    assert error.reason.startswith(reason)
    if key == "colour":
        assert "did you mean" not in error.reason


def test_an_unknown_vss_key_in_a_wire_sample_is_an_unknown_field_not_a_vss_sample():
    error = only_error(sample(**{"Vehicle.Colour": "red"}))
    assert (error.field, error.reason) == ("Vehicle.Colour", "unknown field 'Vehicle.Colour'")


@pytest.mark.parametrize("changes", [{"\udfff": 1.0}, {"vehicle_id": "car\ud800"}, {"speed_mps": "\udfff"}])
def test_a_reason_quoting_a_lone_surrogate_can_be_logged_and_sent(changes):
    # JSON's \\udfff escape gives Python a lone surrogate, which UTF-8 (a log file, a socket) cannot encode
    error = only_error(sample(**changes))
    error.reason.encode("utf-8")
    assert "\\ud" in error.reason


def test_t_s_does_not_replace_timestamp_ms():
    error = only_error(sample(timestamp_ms=DROP, t_s=1.5))
    assert error.field == "t_s"


@pytest.mark.parametrize("name", [c.name for c in TELEMETRY if c.required])
def test_a_missing_required_field_is_named(name):
    error = only_error(sample(**{name: DROP}))
    assert (error.field, error.reason) == (name, f"missing required field '{name}'")


def test_a_sample_without_vehicle_id_takes_the_authenticated_vehicle():
    samples, errors = parse([sample(vehicle_id=DROP)], vehicle_id="car-9")
    assert errors == [] and samples[0]["vehicle_id"] == "car-9"


# ------------------------------------------------------------------------------------------ time and credentials


def test_a_timestamp_too_far_in_the_future_is_refused():
    error = only_error(sample(timestamp_ms=NOW_MS + 3_600_000))
    assert error.field == "timestamp_ms"
    assert error.reason.startswith(f"timestamp_ms {NOW_MS + 3_600_000} is 3600.0 s in the future (limit 60 s")
    samples, errors = parse([sample(timestamp_ms=NOW_MS + 60_000), sample(timestamp_ms=NOW_MS + 60_001)])
    assert len(samples) == 1 and [e.index for e in errors] == [1]
    samples, errors = parse([sample(timestamp_ms=NOW_MS + 60_001)], max_future_ms=120_000)
    assert len(samples) == 1


def test_a_sample_of_another_vehicle_is_refused():
    samples, errors = parse([sample(vehicle_id="car-2"), sample(vehicle_id="car-1")], vehicle_id="car-1")
    assert [s["vehicle_id"] for s in samples] == ["car-1"]
    (error,) = errors
    assert (error.index, error.field) == (0, "vehicle_id")
    assert error.reason == "sample of vehicle 'car-2' sent with the credentials of 'car-1'"
    assert error.vehicle_id == "car-2"


def test_a_sample_error_carries_what_could_be_read_of_the_sample():
    error = only_error(sample(speed_mps="fast"))
    assert error.to_dict() == {
        "index": 0,
        "field": "speed_mps",
        "reason": 'speed_mps must be a number, got string "fast"',
        "vehicle_id": "car-1",
        "timestamp_ms": SAMPLE["timestamp_ms"],
    }
    error = only_error(sample(vehicle_id=7, timestamp_ms="x", speed_mps="fast"))
    assert (error.vehicle_id, error.timestamp_ms) == (None, None)


# ------------------------------------------------------------------------------------------------ payloads


def test_a_bad_ndjson_line_is_an_error_for_that_line_and_the_others_are_kept():
    body = "\n".join(
        [
            json.dumps(sample(timestamp_ms=NOW_MS - 300)),
            '{"speed_mps": 1,',
            "",
            json.dumps(sample(timestamp_ms=NOW_MS - 200)),
            "[1, 2]",
            "   ",
            json.dumps(sample(timestamp_ms=NOW_MS - 100)) + "\r",
        ]
    ).encode()
    samples, errors = parse_payload(body, content_type=NDJSON_TYPE, now_ms=NOW_MS)
    assert [s["timestamp_ms"] for s in samples] == [NOW_MS - 300, NOW_MS - 200, NOW_MS - 100]
    assert [(e.index, e.field) for e in errors] == [(1, None), (4, None)]  # line number - 1; blank lines count
    assert errors[0].reason.startswith("line 2 is not valid JSON")
    assert errors[1].reason == "sample must be a JSON object, got array [1, 2]"


def test_an_ndjson_line_nested_deeper_than_the_stack_is_an_error_for_that_line():
    body = b"[" * 100_000 + b"\n" + body_of([sample()], "ndjson")
    samples, errors = parse_payload(body, content_type=NDJSON_TYPE, now_ms=NOW_MS)
    assert len(samples) == 1
    assert [e.index for e in errors] == [0] and "nested too deeply" in errors[0].reason


def test_ndjson_lines_that_only_parse_together_are_each_refused():
    # As one array these three lines are three objects; line by line none is valid JSON.
    body = b'{"a":"}\n{"}\n{"x":1},{"y":2}\n'
    samples, errors = parse_payload(body, content_type=NDJSON_TYPE, now_ms=NOW_MS)
    assert samples == [] and [e.index for e in errors] == [0, 1, 2]
    assert all("is not valid JSON" in e.reason for e in errors)


def test_an_array_element_that_is_not_an_object_is_an_error_for_that_element():
    samples, errors = parse([1, sample(), "x"])
    assert len(samples) == 1
    assert [(e.index, e.field, e.reason) for e in errors] == [
        (0, None, "sample must be a JSON object, got number 1"),
        (2, None, 'sample must be a JSON object, got string "x"'),
    ]


@pytest.mark.parametrize(
    "body, content_type",
    [
        (b'[{"speed_mps": 1},', JSON_TYPE),
        (b'[{"speed_mps": 1},', None),
        (b'{"speed_mps": 1', JSON_TYPE),
        (b"[" * 100_000, None),
    ],
)
def test_a_json_document_that_does_not_parse_is_a_payload_error(body, content_type):
    with pytest.raises(PayloadError, match="payload is not valid JSON") as err:
        parse_payload(body, content_type=content_type, now_ms=NOW_MS)
    assert err.value.status == 400


def test_ndjson_sent_as_json_is_refused_with_a_hint():
    with pytest.raises(PayloadError, match="application/x-ndjson"):
        parse_payload(body_of([sample(), sample()], "ndjson"), content_type=JSON_TYPE, now_ms=NOW_MS)


@pytest.mark.parametrize("body", [b"42", b'"text"', b"null", b"true"])
@pytest.mark.parametrize("content_type", [JSON_TYPE, None])
def test_a_json_document_that_is_neither_object_nor_array_is_a_payload_error(body, content_type):
    with pytest.raises(PayloadError, match="must be an object .* or an array") as err:
        parse_payload(body, content_type=content_type, now_ms=NOW_MS)
    assert err.value.status == 400


def test_an_oversized_payload_is_refused_with_413_before_it_is_parsed():
    with pytest.raises(PayloadError, match="1001 bytes exceeds the limit of 1000 bytes") as err:
        parse_payload(b"\xff" * 1001, max_bytes=1000, now_ms=NOW_MS)  # not UTF-8: never decoded
    assert err.value.status == 413
    samples, _ = parse_payload(body_of([sample()]), max_bytes=len(body_of([sample()])), now_ms=NOW_MS)
    assert len(samples) == 1


@pytest.mark.parametrize(
    "body, content_type",
    [(b"", None), (b"", JSON_TYPE), (b" \n\t\r\n", None), (b"\n\n", NDJSON_TYPE), (b"[]", JSON_TYPE), (b" [ ] ", None)],
)
def test_a_payload_without_samples_is_a_payload_error(body, content_type):
    with pytest.raises(PayloadError, match="empty payload") as err:
        parse_payload(body, content_type=content_type, now_ms=NOW_MS)
    assert err.value.status == 400


@pytest.mark.parametrize("fmt", ["json", "ndjson"])
def test_too_many_samples_is_a_payload_error(fmt):
    with pytest.raises(PayloadError, match="3 samples, more than the limit of 2") as err:
        parse([sample()] * 3, fmt, max_samples=2)
    assert err.value.status == 413
    samples, _ = parse([sample()] * 2, fmt, max_samples=2)
    assert len(samples) == 2


def test_a_body_that_is_not_utf8_is_a_payload_error():
    with pytest.raises(PayloadError, match="not UTF-8") as err:
        parse_payload(b'{"vehicle_id": "\xe9"}', now_ms=NOW_MS)
    assert err.value.status == 400


def test_an_unknown_content_type_is_refused_with_415():
    with pytest.raises(PayloadError, match="text/csv") as err:
        parse_payload(b"a,b\n1,2", content_type="text/csv", now_ms=NOW_MS)
    assert (err.value.status, err.value.field) == (415, "content_type")


@pytest.mark.parametrize(
    "content_type, fmt",
    [
        ("application/json; charset=utf-8", "json"),
        ("Application/JSON", "json"),
        ("application/jsonl", "ndjson"),
        ("application/x-ndjson; charset=UTF-8", "ndjson"),
        ("application/ndjson", "ndjson"),
        (None, "json"),
        (None, "ndjson"),
    ],
)
def test_content_types_with_parameters_and_any_case_are_understood(content_type, fmt):
    samples, errors = parse_payload(body_of([sample(), sample()], fmt), content_type=content_type, now_ms=NOW_MS)
    assert len(samples) == 2 and errors == []


@pytest.mark.parametrize(
    "body, count",
    [
        (json.dumps(sample()).encode(), 1),  # one object: an MQTT message of one sample
        (b"  \n" + json.dumps([sample(), sample()]).encode(), 2),  # an array
        (body_of([sample(), sample(), sample()], "ndjson"), 3),  # NDJSON
        (b"{bad\n" + body_of([sample()], "ndjson"), 1),  # NDJSON whose first line is bad
        ("\ufeff".encode() + json.dumps(sample()).encode(), 1),  # a byte order mark
    ],
)
def test_without_a_content_type_the_format_is_detected(body, count):
    samples, errors = parse_payload(body, now_ms=NOW_MS)
    assert len(samples) == count
    assert len(errors) == (1 if body.startswith(b"{bad") else 0)


def test_bad_options_are_programming_errors_not_payload_errors():
    with pytest.raises(TypeError, match="body must be bytes"):
        parse_payload("{}", now_ms=NOW_MS)
    with pytest.raises(ValueError, match="max_samples must be an integer >= 1, got 0") as err:
        parse_payload(b"{}", now_ms=NOW_MS, max_samples=0)
    assert not isinstance(err.value, PayloadError)
    with pytest.raises(ValueError, match="now_ms must be an integer"):
        parse_payload(b"{}", now_ms=1.7e12)
    with pytest.raises(ValueError, match="vehicle_id must be None or match"):
        parse_payload(b"{}", now_ms=NOW_MS, vehicle_id="no spaces")


# ------------------------------------------------------------------------------------------------------- VSS


def vss_sample(**changes) -> dict:
    out = {
        "Vehicle.VehicleIdentification.VIN": "WVWZZZ1JZXW000001",
        "timestamp_ms": NOW_MS - 1_000,
        "Vehicle.CurrentLocation.Latitude": 38.04,
        "Vehicle.CurrentLocation.Longitude": 114.51,
        "Vehicle.Speed": 100,
        "Vehicle.Acceleration.Longitudinal": 0.5,
        "Vehicle.Acceleration.Lateral": -0.2,
        "Vehicle.AngularVelocity.Yaw": 90,
        "Vehicle.Chassis.SteeringWheel.Angle": 180.0,
        "Vehicle.Chassis.Axle.Row1.Wheel.Left.AngularSpeed": 180.0,
        "Vehicle.Chassis.Axle.Row1.Wheel.Right.AngularSpeed": 360.0,
        "Vehicle.Chassis.Axle.Row2.Wheel.Left.AngularSpeed": 540.0,
        "Vehicle.Chassis.Axle.Row2.Wheel.Right.AngularSpeed": 720.0,
        "Vehicle.ADAS.ABS.IsEngaged": True,
        "Vehicle.ADAS.CruiseControl.IsActive": False,
        **changes,
    }
    return {k: v for k, v in out.items() if v is not DROP}


def test_a_vss_sample_converts_to_wire_format_with_exact_units():
    samples, errors = parse([vss_sample(**{"Vehicle.MotionManagement.Steering.SteeringWheel.Torque": 1.5})])
    assert errors == []
    assert samples == [
        {
            "vehicle_id": "WVWZZZ1JZXW000001",
            "timestamp_ms": NOW_MS - 1_000,
            "latitude_deg": 38.04,
            "longitude_deg": 114.51,
            "speed_mps": 100 / 3.6,
            "accel_lon_mps2": 0.5,
            "accel_lat_mps2": -0.2,
            "yaw_rate_radps": math.pi / 2,
            "steering_wheel_angle_rad": math.pi,
            "wheel_speed_fl_radps": math.pi,
            "wheel_speed_fr_radps": 2 * math.pi,
            "wheel_speed_rl_radps": 3 * math.pi,
            "wheel_speed_rr_radps": 4 * math.pi,
            "abs_active": True,
            "acc_active": False,
            "tcs_active": None,
            "esc_active": None,
            "lateral_speed_mps": None,
            "gnss_speed_mps": None,
            "gnss_speed_accuracy_mps": None,
            "drive_force_n": None,
            "brake_force_n": None,
            "steering_torque_nm": 1.5,
            "eps_assist_torque_nm": None,
        }
    ]
    assert samples[0]["speed_mps"] == 27.77777777777778 and list(samples[0]) == list(TELEMETRY_COLUMNS)


def test_tcs_and_esc_flags_are_optional_booleans_in_both_key_sets():
    samples, errors = parse(
        [
            vss_sample(**{"Vehicle.ADAS.TCS.IsEngaged": True, "Vehicle.ADAS.ESC.IsEngaged": False}),
            sample(tcs_active=False, esc_active=True),
            sample(tcs_active=None),
        ]
    )
    assert errors == []
    assert [(s["tcs_active"], s["esc_active"]) for s in samples] == [(True, False), (False, True), (None, None)]
    _, errors = parse([sample(tcs_active=1), vss_sample(**{"Vehicle.ADAS.ESC.IsEngaged": "yes"})])
    assert [(e.field, e.reason) for e in errors] == [
        ("tcs_active", "tcs_active must be true or false, got number 1"),
        ("Vehicle.ADAS.ESC.IsEngaged", 'Vehicle.ADAS.ESC.IsEngaged must be true or false, got string "yes"'),
    ]


def test_every_vss_key_maps_to_a_wire_field():
    # VSS has no lateral speed, GNSS Doppler speed, drive or brake force, nor EPS assist torque
    no_vss = {"timestamp_ms", "lateral_speed_mps", *CHANNEL_NAMES} - {"steering_torque_nm"}
    assert {s.wire for s in VSS.values()} == set(TELEMETRY_COLUMNS) - no_vss


def test_a_vss_sample_may_carry_vehicle_id_as_a_plain_key_or_take_the_authenticated_one():
    samples, _ = parse([vss_sample(**{"Vehicle.VehicleIdentification.VIN": DROP, "vehicle_id": "car-1"})])
    assert samples[0]["vehicle_id"] == "car-1"
    samples, _ = parse([vss_sample(**{"Vehicle.VehicleIdentification.VIN": DROP})], vehicle_id="car-3")
    assert samples[0]["vehicle_id"] == "car-3"


VSS_ERRORS = [
    ({"Vehicle.Speed": 400}, "Vehicle.Speed", "Vehicle.Speed 400 outside [-18, 360] km/h"),
    (
        {"Vehicle.AngularVelocity.Yaw": -200.0},
        "Vehicle.AngularVelocity.Yaw",
        "Vehicle.AngularVelocity.Yaw -200.0 outside [-171.887, 171.887] deg/s",
    ),
    ({"Vehicle.Speed": "12"}, "Vehicle.Speed", 'Vehicle.Speed must be a number, got string "12"'),
    ({"Vehicle.Speed": math.nan}, "Vehicle.Speed", "Vehicle.Speed must be finite, got NaN"),
    ({"Vehicle.Speed": 10**400}, "Vehicle.Speed", "Vehicle.Speed 1000000000"),
    (
        {"Vehicle.ADAS.ABS.IsEngaged": "yes"},
        "Vehicle.ADAS.ABS.IsEngaged",
        'Vehicle.ADAS.ABS.IsEngaged must be true or false, got string "yes"',
    ),
    ({"Vehicle.Speed": DROP}, "Vehicle.Speed", "missing required field 'Vehicle.Speed'"),
    ({"timestamp_ms": DROP}, "timestamp_ms", "missing required field 'timestamp_ms' (VSS has no sample time"),
    (
        {"Vehicle.VehicleIdentification.VIN": DROP},
        "Vehicle.VehicleIdentification.VIN",
        "missing required field 'Vehicle.VehicleIdentification.VIN' (or 'vehicle_id')",
    ),
    ({"Vehicle.Sped": 1.0}, "Vehicle.Sped", "unknown field 'Vehicle.Sped' (did you mean 'Vehicle.Speed'?)"),
    ({"speed_mps": 1.0}, "speed_mps", "wire field 'speed_mps' mixed with VSS keys"),
    ({"speed_mps": 1.0, "colour": 1}, "colour", "unknown field 'colour'"),  # unknown keys first, then mixing
    (
        {"Vehicle.VehicleIdentification.VIN": "no spaces"},
        "Vehicle.VehicleIdentification.VIN",
        'Vehicle.VehicleIdentification.VIN "no spaces" must be 1-64 characters',
    ),
    (
        {"vehicle_id": "car-1"},
        "Vehicle.VehicleIdentification.VIN",
        'Vehicle.VehicleIdentification.VIN "WVWZZZ1JZXW000001" and vehicle_id "car-1" differ',
    ),
]


@pytest.mark.parametrize("changes, field, reason", VSS_ERRORS, ids=[e[1] + "-" + e[2][:30] for e in VSS_ERRORS])
def test_errors_on_a_vss_sample_name_the_vss_key_sent(changes, field, reason):
    error = only_error(vss_sample(**changes))
    assert error.field == field
    assert reason in error.reason


def test_a_vss_sample_of_another_vehicle_names_the_vin():
    error = only_error(vss_sample(), vehicle_id="car-1")
    assert error.field == "Vehicle.VehicleIdentification.VIN"
    assert error.reason == "sample of vehicle 'WVWZZZ1JZXW000001' sent with the credentials of 'car-1'"


# ------------------------------------------------------------------------------------------------ properties

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=10), inner, max_size=3),
    max_leaves=6,
)


@st.composite
def valid_samples(draw):
    out = {
        "vehicle_id": draw(st.from_regex(VEHICLE_ID_RE, fullmatch=True)),
        "timestamp_ms": draw(st.integers(0, NOW_MS + 60_000)),
    }
    for c in TELEMETRY:
        if c.name in out:
            continue
        if c.name in RANGES:
            low, high = RANGES[c.name]
            value = draw(st.floats(low, high) | st.integers(math.ceil(low), math.floor(high)))
        else:
            value = draw(st.booleans())
        if c.required or draw(st.booleans()):
            out[c.name] = value
        elif draw(st.booleans()):
            out[c.name] = None
    return out


def normalized(s: dict) -> dict:
    return {
        name: (float(s[name]) if name in RANGES and s.get(name) is not None else s.get(name))
        for name in TELEMETRY_COLUMNS
    }


@st.composite
def entries(draw):
    """(kind, value): a valid sample, a valid sample with one key set to any JSON value, or any JSON value."""
    kind = draw(st.sampled_from(["valid", "mutated", "junk"]))
    if kind == "junk":
        return kind, draw(json_values)
    s = draw(valid_samples())
    if kind == "mutated":
        key = draw(st.sampled_from(TELEMETRY_COLUMNS) | st.text(max_size=12) | st.sampled_from(list(VSS)))
        s[key] = draw(json_values)
    return kind, s


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(entries(), min_size=1, max_size=8), st.sampled_from(["json", "ndjson", "object"]), st.booleans())
@pytest.mark.slow
def test_any_json_mixed_into_valid_samples_loses_no_valid_sample_and_reports_each_bad_one_once(items, fmt, detect):
    kinds, values = [k for k, _ in items], [v for _, v in items]
    if fmt == "object":
        kinds, values = kinds[:1], values[:1]
        body = json.dumps(values[0]).encode()
    else:
        body = body_of(values, fmt)
    content_type = None if detect else {"json": JSON_TYPE, "ndjson": NDJSON_TYPE, "object": JSON_TYPE}[fmt]
    # The body as one JSON document: the whole of it is a sample (an object), the samples (an array) or no payload.
    whole = fmt == "object" or (detect and fmt == "ndjson" and len(values) == 1)
    refused = (whole and (type(values[0]) not in (dict, list) or values[0] == [])) or (
        detect and fmt == "ndjson" and len(values) > 1 and type(values[0]) is list
    )  # detected as an array: bad JSON
    if whole and type(values[0]) is list:
        kinds, values = ["junk"] * len(values[0]), values[0]
    try:
        samples, errors = parse_payload(body, content_type=content_type, now_ms=NOW_MS)
    except PayloadError:
        assert refused
        return
    assert not refused
    n = len(values)
    failed = [e.index for e in errors]
    assert len(samples) + len(errors) == n
    assert len(set(failed)) == len(failed) and all(0 <= i < n for i in failed)
    kept = [i for i in range(n) if i not in set(failed)]
    for i, s in zip(kept, samples):
        assert list(s) == list(TELEMETRY_COLUMNS)
        if kinds[i] == "valid":
            assert s == normalized(values[i])
    assert all(kinds[i] != "valid" for i in failed), [(e.index, e.reason) for e in errors]


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200) | st.text(max_size=200).map(str.encode), st.sampled_from([None, JSON_TYPE, NDJSON_TYPE]))
def test_any_bytes_give_samples_and_errors_or_a_payload_error_never_another_exception(body, content_type):
    try:
        samples, errors = parse_payload(body, content_type=content_type, now_ms=NOW_MS)
    except PayloadError as e:
        assert e.status == 400
        return
    assert all(list(s) == list(TELEMETRY_COLUMNS) for s in samples)
    assert len({e.index for e in errors}) == len(errors)
    if content_type == NDJSON_TYPE:
        lines = [line for line in body.decode().split("\n") if line.strip(" \t\r")]
        assert len(samples) + len(errors) == len(lines)


# ------------------------------------------------------------------------------------------- optional channels


def test_optional_channels_are_accepted_and_absent_ones_are_none_never_zero():
    channels = {"gnss_speed_mps": 20.1, "gnss_speed_accuracy_mps": 0.06, "drive_force_n": 850.0, "brake_force_n": 0.0}
    samples, errors = parse([sample(**channels), sample(timestamp_ms=NOW_MS - 900)])
    assert errors == []
    assert {k: samples[0][k] for k in channels} == channels
    assert samples[0]["steering_torque_nm"] is None and samples[0]["eps_assist_torque_nm"] is None
    assert all(samples[1][k] is None for k in CHANNEL_NAMES)


@pytest.mark.parametrize(
    "field, value, reason",
    [
        ("brake_force_n", -10.0, "brake_force_n -10.0 outside [0, 150000] N"),
        ("gnss_speed_mps", "20", "gnss_speed_mps must be a number"),
        ("steering_torque_nm", 500.0, "steering_torque_nm 500.0 outside [-100, 100] N m"),
    ],
)
def test_a_bad_optional_channel_is_refused_naming_it(field, value, reason):
    error = only_error(sample(**{field: value}))
    assert error.field == field and error.reason.startswith(reason), error.reason
