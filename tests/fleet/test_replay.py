"""Replay of recorded telemetry (roadgrip/fleet/replay.py): pacing on a fake clock, batching, nothing rewritten."""

import copy
import math
from pathlib import Path

import pyarrow as pa
import pytest

from roadgrip.data.tables import write_table
from roadgrip.data.telemetry import validate_telemetry
from roadgrip.fleet.importers.bmw_m8 import DEFAULT_START_MS
from roadgrip.fleet.replay import ReplayResult, replay, replay_file

ROOT = Path(__file__).resolve().parents[2]
LOG = ROOT / "data" / "real" / "bmw_m8_braking"  # the real log, kept in the repository (its README: source, licence)


class FakeClock:
    """monotonic() and sleep() on simulated time; `send` may advance it to play a slow transport."""

    def __init__(self, t: float = 1000.0):
        self.t = t
        self.sleeps = []

    def monotonic(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        assert seconds > 0
        self.sleeps.append(seconds)
        self.t += seconds


def samples(n=10, vehicle="v1", t0=1_700_000_000_000, dt_ms=100):
    return [{"vehicle_id": vehicle, "timestamp_ms": t0 + i * dt_ms, "speed_mps": float(i)} for i in range(n)]


class Recorder:
    def __init__(self, clock):
        self.clock, self.calls = clock, []

    def __call__(self, batch):
        self.calls.append((self.clock.t, list(batch)))


def test_real_time_replay_sends_each_sample_when_it_is_due():
    clock = FakeClock()
    sent = Recorder(clock)
    result = replay(samples(10), sent, clock=clock)
    assert result == ReplayResult(samples=10, batches=10, late_batches=0, max_delay_s=0.0, wall_s=pytest.approx(0.9))
    assert [t - 1000.0 for t, _ in sent.calls] == pytest.approx([0.1 * i for i in range(10)])
    assert [len(b) for _, b in sent.calls] == [1] * 10


@pytest.mark.parametrize("speed", [2.0, 10.0])
def test_speed_scales_the_pace(speed):
    clock = FakeClock()
    sent = Recorder(clock)
    replay(samples(10), sent, speed=speed, clock=clock)
    assert [t - 1000.0 for t, _ in sent.calls] == pytest.approx([0.1 * i / speed for i in range(10)])


@pytest.mark.parametrize("speed", [0, 0.0, math.inf])
def test_speed_zero_or_infinite_never_waits(speed):
    clock = FakeClock()
    sent = Recorder(clock)
    result = replay(samples(50), sent, speed=speed, batch=7, clock=clock)
    assert clock.sleeps == [] and result.wall_s == 0.0
    assert result.samples == 50 and result.batches == 8 and sum(len(b) for _, b in sent.calls) == 50


def test_batches_go_out_when_their_last_sample_is_due():
    clock = FakeClock()
    sent = Recorder(clock)
    result = replay(samples(10), sent, batch=3, clock=clock)
    assert result.batches == 4
    assert [len(b) for _, b in sent.calls] == [3, 3, 3, 1]
    assert [t - 1000.0 for t, _ in sent.calls] == pytest.approx([0.2, 0.5, 0.8, 0.9])


def test_samples_are_sent_in_time_order_and_unchanged():
    data = samples(10)
    shuffled = [data[i] for i in (3, 0, 9, 1, 2, 8, 4, 7, 5, 6)]
    before = copy.deepcopy(shuffled)
    clock = FakeClock()
    sent = Recorder(clock)
    replay(shuffled, sent, batch=4, clock=clock)
    out = [s for _, b in sent.calls for s in b]
    assert [s["timestamp_ms"] for s in out] == sorted(s["timestamp_ms"] for s in data)
    assert all(any(s is d for d in data) for s in out)  # the very objects, not copies
    assert shuffled == before  # nothing rewritten, the input list not reordered


def test_equal_timestamps_keep_their_order():
    data = [{"vehicle_id": "v1", "timestamp_ms": 5, "n": i} for i in range(3)] + [
        {"vehicle_id": "v1", "timestamp_ms": 1, "n": 9}
    ]
    clock = FakeClock()
    sent = Recorder(clock)
    replay(data, sent, speed=0, clock=clock)
    assert [b[0]["n"] for _, b in sent.calls] == [9, 0, 1, 2]


def test_each_batch_holds_one_vehicle():
    data = samples(7, "a") + samples(5, "b", t0=1_700_000_000_050)
    clock = FakeClock()
    sent = Recorder(clock)
    result = replay(data, sent, batch=3, clock=clock)
    assert all(len({s["vehicle_id"] for s in b}) == 1 for _, b in sent.calls)
    assert sorted(len(b) for _, b in sent.calls) == [1, 2, 3, 3, 3]
    assert result.samples == 12 and result.batches == 5
    # b's last, partial batch goes out when b's last sample is due: 50 ms + 4 x 100 ms after the start
    last_b = [t for t, b in sent.calls if b[0]["vehicle_id"] == "b"][-1]
    assert last_b - 1000.0 == pytest.approx(0.45)


def test_a_slow_sender_makes_batches_late_without_drift():
    clock = FakeClock()

    def slow(batch):
        clock.t += 0.25  # each call takes 250 ms, samples come every 100 ms

    result = replay(samples(10), slow, clock=clock)
    assert result.batches == 10 and result.late_batches == 9
    assert result.wall_s == pytest.approx(2.5)  # back-to-back sends; no sleeps once behind
    assert clock.sleeps == []
    assert result.max_delay_s == pytest.approx(2.25 - 0.9)


def test_sleeping_clock_catches_up_after_one_slow_send():
    clock = FakeClock()
    times = []

    def once_slow(batch):
        times.append(clock.t)
        if len(times) == 2:
            clock.t += 0.35

    replay(samples(6), once_slow, clock=clock)
    # sample 2 (due 0.2) waits for the slow send (until 0.45); from sample 5 (due 0.5) on, back on schedule
    assert [t - 1000.0 for t in times] == pytest.approx([0.0, 0.1, 0.45, 0.45, 0.45, 0.5])


def test_empty_replay():
    assert replay([], lambda b: None, clock=FakeClock()) == ReplayResult(0, 0, 0, 0.0, 0.0)


def test_an_exception_of_send_propagates():
    def broken(batch):
        raise ConnectionError("down")

    with pytest.raises(ConnectionError):
        replay(samples(3), broken, clock=FakeClock())


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"speed": -1.0}, "speed"),
        ({"speed": float("nan")}, "speed"),
        ({"speed": "fast"}, "speed"),
        ({"batch": 0}, "batch"),
        ({"batch": 2.5}, "batch"),
        ({"batch": True}, "batch"),
    ],
)
def test_bad_arguments_are_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        replay(samples(3), lambda b: None, clock=FakeClock(), **kwargs)


def test_a_sample_without_an_integer_timestamp_is_an_error():
    data = samples(3)
    data[1]["timestamp_ms"] = 1.5e12
    with pytest.raises(TypeError, match="sample 1 .*timestamp_ms"):
        replay(data, lambda b: None, clock=FakeClock())
    with pytest.raises(TypeError, match="sample 0"):
        replay(["x"], lambda b: None, clock=FakeClock())


# ------------------------------------------------------------------------------------------------- replay_file


def test_replay_file_detects_the_bmw_log_and_returns_wire_samples():
    out = replay_file(LOG)
    assert len(out) > 80
    assert out[0]["timestamp_ms"] == DEFAULT_START_MS and out[0]["vehicle_id"] == "bmw-m8"
    assert [s["timestamp_ms"] for s in out] == list(range(DEFAULT_START_MS, DEFAULT_START_MS + 100 * len(out), 100))
    assert validate_telemetry(pa.Table.from_pylist(out)).rejections == []


def test_replay_file_options_and_importer_by_name(tmp_path):
    out = replay_file(LOG, "bmw-m8", vehicle_id="m8-test", start_ms=1_000)
    assert {s["vehicle_id"] for s in out} == {"m8-test"} and out[0]["timestamp_ms"] == 1_000
    with pytest.raises(ValueError, match="importer must be one of"):
        replay_file(LOG, "no-such-logger")
    with pytest.raises(ValueError, match="unknown option"):
        replay_file(LOG, colour="red")


def test_replay_of_an_imported_log_delivers_it_whole(tmp_path):
    """Import, write as NDJSON, replay the file on a fake clock at 10 x real time in batches of 10: what arrives is
    what the importer produced, in order, in the time the log lasted / 10."""
    imported = replay_file(LOG)
    path = write_table(pa.Table.from_pylist(imported), tmp_path / "m8.ndjson")
    again = replay_file(path)  # the wire importer recognises the file
    assert again == imported
    clock = FakeClock()
    received = []
    result = replay(again, received.extend, speed=10.0, batch=10, clock=clock)
    assert received == imported
    assert result.wall_s == pytest.approx((imported[-1]["timestamp_ms"] - imported[0]["timestamp_ms"]) / 10_000)
    assert result.late_batches == 0


def test_replay_file_leaves_absent_optional_fields_out(tmp_path):
    rows = [
        {
            "vehicle_id": "v1",
            "t_s": 0.1 * i,
            "speed_mps": 10.0,
            "accel_lon_mps2": 0.0,
            "accel_lat_mps2": 0.0,
            "yaw_rate_radps": 0.0,
            "steering_wheel_angle_rad": 0.0,
            **{f"wheel_speed_{w}_radps": 30.0 for w in ("fl", "fr", "rl", "rr")},
            "abs_active": False,
            "acc_active": False,
        }
        for i in range(30)
    ]
    path = write_table(pa.Table.from_pylist(rows), tmp_path / "drive.csv")
    out = replay_file(path, start_ms=1_700_000_000_000)
    assert len(out) == 30 and "latitude_deg" not in out[0] and "lateral_speed_mps" not in out[0]
    assert [s["timestamp_ms"] for s in out[:3]] == [1_700_000_000_000, 1_700_000_000_100, 1_700_000_000_200]
