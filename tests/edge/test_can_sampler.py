"""The live-CAN input of `roadgrip edge` (roadgrip/edge/sources.py, `CanSampler`) on python-can's virtual bus: frames
of the Toyota RAV4 2019 encoded with cantools from its DBC (data/real/toyota_rav4_street) as the car's ECUs would
send them, 10 Hz each, read back through the mapping `import-log` uses (roadgrip/fleet/importers/toyota_rav4_2019.yaml)
into wire-format samples that hold the encoded values in SI units."""

from __future__ import annotations

import math
import uuid
from pathlib import Path

import can
import pytest

from roadgrip.edge.sources import CanSampler
from roadgrip.fleet.importers.can_dbc import load_dbc

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "data" / "real" / "toyota_rav4_street" / "toyota_rav4_2019.dbc"
MAPPING = ROOT / "roadgrip" / "fleet" / "importers" / "toyota_rav4_2019.yaml"
WHEEL_RADIUS_M = 0.355  # toyota_rav4_2019_profile.yaml
T0_S = 1_700_000_000.0  # a grid instant (a multiple of 100 ms)
TICKS = 40


def raw_values(k: int) -> dict[str, dict[str, int]]:
    """Tick k's raw (integer) value of every mapped signal, by message: different at every tick."""
    return {
        "SPEED": {"SPEED": 5000 + 7 * k},
        "KINEMATICS": {"ACCEL_X": 512 + k % 20 - 10, "ACCEL_Y": 500 + k % 7, "YAW_RATE": 512 + k % 11 - 5},
        "STEER_ANGLE_SENSOR": {"STEER_ANGLE": k % 9 - 4, "STEER_FRACTION": k % 5 - 2},
        "WHEEL_SPEEDS": {f"WHEEL_SPEED_{w}": 11767 + 5 * k + i for i, w in enumerate(("FL", "FR", "RL", "RR"))},
        "PCM_CRUISE": {"CRUISE_ACTIVE": k % 2},
        "STEER_TORQUE_SENSOR": {"STEER_TORQUE_DRIVER": 100 - k, "STEER_TORQUE_EPS": 50 + k},
    }


def physical(db, message: str, raw: dict[str, int]) -> dict[str, float]:
    signals = {s.name: s for s in db.get_message_by_name(message).signals}
    return {name: value * signals[name].scale + signals[name].offset for name, value in raw.items()}


def expected_sample(db, k: int) -> dict:
    """Tick k's values as wire format v1 fields, converted here from the DBC's units (km/h, deg, deg/s, counts)."""
    v = {name: value for message, raw in raw_values(k).items() for name, value in physical(db, message, raw).items()}
    sample = {
        "speed_mps": v["SPEED"] / 3.6,
        "accel_lon_mps2": v["ACCEL_X"],
        "accel_lat_mps2": v["ACCEL_Y"],
        "yaw_rate_radps": math.radians(v["YAW_RATE"]),
        "steering_wheel_angle_rad": math.radians(v["STEER_ANGLE"] + v["STEER_FRACTION"]),
        "acc_active": bool(v["CRUISE_ACTIVE"]),
        "abs_active": False,  # the mapping's constant: this DBC decodes no ABS flag
        "steering_torque_nm": v["STEER_TORQUE_DRIVER"] * 0.01,  # the mapping's nominal scale
        "eps_assist_torque_nm": v["STEER_TORQUE_EPS"] * 0.01,
    }
    for wheel in ("fl", "fr", "rl", "rr"):
        sample[f"wheel_speed_{wheel}_radps"] = v[f"WHEEL_SPEED_{wheel.upper()}"] / 3.6 / WHEEL_RADIUS_M
    return sample


def send_drive(bus: can.BusABC, db) -> None:
    """TICKS ticks of every mapped message 10 ms after each grid instant, and a frame of an unmapped id among them."""
    for k in range(TICKS):
        for j, (name, raw) in enumerate(raw_values(k).items()):
            message = db.get_message_by_name(name)
            values = {s.name: 0 for s in message.signals} | physical(db, name, raw)  # checksums and the rest: 0
            data = message.encode(values, strict=False)
            stamp = T0_S + k * 0.1 + 0.01 + j * 0.001
            bus.send(can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False, timestamp=stamp))
        bus.send(can.Message(arbitration_id=0x7F0, data=b"\xff" * 8, is_extended_id=False, timestamp=stamp + 0.001))


def test_frames_encoded_from_the_dbc_come_back_as_the_samples_they_encode():
    db = load_dbc(DBC)
    channel = f"roadgrip-test-{uuid.uuid4().hex}"
    with (
        can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as car,
        can.Bus(interface="virtual", channel=channel) as terminal,
    ):
        send_drive(car, db)
        sampler = CanSampler(terminal, DBC, MAPPING, "rav4-on-bus", idle_timeout_s=0.2)
        samples = list(sampler)
    # grid instant k + 1 holds tick k's frames (the latest at or before it); the last tick's instant needs a later
    # frame to be known complete, which never comes
    assert [s["timestamp_ms"] for s in samples] == [int(T0_S * 1000) + 100 * (k + 1) for k in range(TICKS - 1)]
    assert sampler.undecodable == 0
    for k, sample in enumerate(samples):
        assert sample["vehicle_id"] == "rav4-on-bus"
        expected = expected_sample(db, k)
        for field, value in expected.items():
            assert sample[field] == pytest.approx(value, rel=1e-12, abs=1e-12), (k, field)
        unmapped = {f: v for f, v in sample.items() if f not in expected and f not in ("vehicle_id", "timestamp_ms")}
        assert all(v is None for v in unmapped.values()), unmapped


def test_a_signal_that_stops_ends_the_samples_after_its_age_limit():
    db = load_dbc(DBC)
    channel = f"roadgrip-test-{uuid.uuid4().hex}"
    with (
        can.Bus(interface="virtual", channel=channel, preserve_timestamps=True) as car,
        can.Bus(interface="virtual", channel=channel) as terminal,
    ):
        send_drive(car, db)  # every message for TICKS ticks, then everything but SPEED for as long again
        for k in range(TICKS, 2 * TICKS):
            for j, (name, raw) in enumerate(raw_values(k).items()):
                if name == "SPEED":
                    continue
                message = db.get_message_by_name(name)
                data = message.encode({s.name: 0 for s in message.signals} | physical(db, name, raw), strict=False)
                stamp = T0_S + k * 0.1 + 0.01 + j * 0.001
                car.send(can.Message(arbitration_id=message.frame_id, data=data, timestamp=stamp))
        samples = list(CanSampler(terminal, DBC, MAPPING, "rav4-on-bus", idle_timeout_s=0.2))
    # SPEED's last frame came 10 ms after instant TICKS - 1; its max_age_s (the mapping's 0.3 s) keeps it for the
    # three instants after that one, then no sample can be made
    assert samples[-1]["timestamp_ms"] == int(T0_S * 1000) + 100 * (TICKS + 2)
    assert len(samples) == TICKS + 2
