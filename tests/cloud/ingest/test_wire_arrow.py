"""Arrow IPC stream payloads (CONTRACTS 3.1, roadgrip/cloud/ingest/wire.py): the same samples as JSON gives, the same
per-sample refusals, and a stream that cannot be used refused whole with one line naming what is wrong."""

import dataclasses
import io

import pyarrow as pa
import pytest

from roadgrip.cloud.ingest.wire import PayloadError, arrow_payload, is_arrow, parse_payload
from roadgrip.data.schema import TELEMETRY_COLUMNS
from roadgrip.data.telemetry import TELEMETRY_SCHEMA
from roadgrip.sim.presets import paper_scenarios
from roadgrip.sim.simulate import simulate

ARROW = "application/vnd.apache.arrow.stream"


@pytest.fixture(scope="module")
def simulated() -> list[dict]:
    run = dataclasses.replace(paper_scenarios()[0], duration_s=3.0)
    return simulate([run]).select(list(TELEMETRY_COLUMNS)).to_pylist()


def stream(table: pa.Table) -> bytes:
    sink = io.BytesIO()
    with pa.ipc.new_stream(sink, table.schema) as writer:
        writer.write_table(table)
    return sink.getvalue()


def refused(body: bytes, **options) -> PayloadError:
    with pytest.raises(PayloadError) as caught:
        parse_payload(body, content_type=ARROW, now_ms=2**50, **options)
    assert "\n" not in str(caught.value)
    return caught.value


def test_arrow_gives_exactly_what_json_gives(simulated):
    now_ms = simulated[-1]["timestamp_ms"]
    samples, errors = parse_payload(arrow_payload(simulated), content_type=ARROW, now_ms=now_ms)
    assert errors == []
    assert samples == simulated
    assert all(list(s) == list(TELEMETRY_COLUMNS) for s in samples)
    # over MQTT there is no content type: the first byte says Arrow
    body = arrow_payload(simulated)
    assert is_arrow(body) and not is_arrow(b'[{"vehicle_id": "x"}]')
    assert parse_payload(body, now_ms=now_ms) == (samples, [])


def test_narrow_types_and_absent_optional_columns_are_taken(simulated):
    table = pa.Table.from_pylist(simulated[:5]).drop_columns(["lateral_speed_mps", "latitude_deg"])
    table = table.set_column(
        table.schema.get_field_index("speed_mps"), "speed_mps", table["speed_mps"].cast(pa.float32())
    ).set_column(table.schema.get_field_index("timestamp_ms"), "timestamp_ms", table["timestamp_ms"].cast(pa.uint64()))
    samples, errors = parse_payload(stream(table), content_type=ARROW, now_ms=2**50)
    assert errors == []
    assert [s["latitude_deg"] for s in samples] == [None] * 5
    assert [s["timestamp_ms"] for s in samples] == [s["timestamp_ms"] for s in simulated[:5]]
    assert [s["speed_mps"] for s in samples] == [
        float(pa.scalar(s["speed_mps"], pa.float32()).as_py()) for s in simulated[:5]
    ]


def test_a_bad_row_is_refused_alone_with_the_json_checks_words(simulated):
    rows = [dict(s) for s in simulated[:6]]
    rows[1]["speed_mps"] = 500.0
    rows[3]["timestamp_ms"] = 2**51  # beyond the clock
    rows[4]["wheel_speed_fl_radps"] = float("nan")
    rows[5]["vehicle_id"] = "someone-else"
    samples, errors = parse_payload(
        arrow_payload(rows), content_type=ARROW, now_ms=2**50, vehicle_id=rows[0]["vehicle_id"]
    )
    assert samples == [rows[0], rows[2]]
    assert [(e.index, e.field) for e in errors] == [
        (1, "speed_mps"),
        (3, "timestamp_ms"),
        (4, "wheel_speed_fl_radps"),
        (5, "vehicle_id"),
    ]
    assert errors[0].reason == "speed_mps 500.0 outside [-5, 100] m/s"
    assert errors[2].reason == "wheel_speed_fl_radps must be finite, got NaN"
    assert "credentials" in errors[3].reason


def test_a_null_in_a_required_column_refuses_that_row(simulated):
    table = pa.Table.from_pylist(simulated[:3])
    table = table.set_column(table.schema.get_field_index("abs_active"), "abs_active", pa.array([True, None, False]))
    samples, errors = parse_payload(stream(table), content_type=ARROW, now_ms=2**50)
    assert len(samples) == 2
    assert [(e.index, e.field) for e in errors] == [(1, "abs_active")]
    assert "null" in errors[0].reason


@pytest.mark.parametrize(
    "change, status, words",
    [
        (lambda body, t: body[:60], 400, "not an Arrow IPC stream"),
        (lambda body, t: b"\xff\xff\xff\xff" + b"\x00" * 3, 400, "not an Arrow IPC stream"),
        (
            lambda body, t: stream(t.rename_columns([*t.column_names[:-1], "speed_kmh"])),
            400,
            "unknown field 'speed_kmh'",
        ),
        (lambda body, t: stream(t.drop_columns(["speed_mps"])), 400, "missing required column 'speed_mps'"),
        (
            lambda body, t: stream(t.set_column(4, "speed_mps", t["speed_mps"].cast(pa.string()))),
            400,
            "column 'speed_mps' has type string",
        ),
        (lambda body, t: stream(t.slice(0, 0)), 400, "no rows"),
        (lambda body, t: body + b"x" * 2_000_000, 413, "exceeds the limit"),
    ],
    ids=["truncated", "garbage", "unknown column", "missing column", "wrong type", "empty", "too large"],
)
def test_an_unusable_stream_is_refused_whole_naming_the_problem(simulated, change, status, words):
    table = pa.Table.from_pylist(simulated[:4], schema=TELEMETRY_SCHEMA)
    error = refused(change(arrow_payload(simulated[:4]), table))
    assert error.status == status
    assert words in str(error)


def test_more_rows_than_the_limit_is_413(simulated):
    error = refused(arrow_payload(simulated[:20]), max_samples=10)
    assert error.status == 413
