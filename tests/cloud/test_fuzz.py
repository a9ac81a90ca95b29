"""Hostile input against the running service, generated: what the cloud survives. SQLite only: the storage layer is
tested on SQLite and PostgreSQL elsewhere (test_storage.py, test_api.py), hostile strings on both in test_access.py.

| test | cases (max_examples x parameters) | what must hold |
| --- | --- | --- |
| schemathesis: each operation of /openapi.json, positive and negative data, as the admin, a vehicle, a reader and nobody | SCHEMA_EXAMPLES x 88 = 5,280 | never a 5xx; status codes, content types, bodies and headers as the OpenAPI declares them; no 2xx without valid credentials (also probed by removing or spoiling them); data outside the schema refused |
| HTTP ingest: any JSON, valid samples with one field set to any JSON, any bytes, NDJSON with junk lines | INGEST_EXAMPLES x 4 = 2,400 | never a 5xx; each rejection has its index, field or null and a reason; the rows stored are exactly the answer's `stored`; every valid sample is stored as sent |
| MQTT handler (`Ingest.mqtt_message`, roadgrip/cloud/ingest/admission.py): any JSON, valid samples with one field mutated, any bytes | MQTT_EXAMPLES x 3 = 2,400 | never raises; each message is acknowledged exactly once, at once when nothing in it is valid, else after its samples are stored; rejections published on the vehicle's error topic with reasons; valid samples stored |

10,080 cases in all; about 2.5 min on two cores (`pytest tests/cloud/test_fuzz.py --hypothesis-show-statistics`
prints the cases each test ran). The ingest tests run with the rate limit off: they post thousands of samples for one
vehicle in seconds (tests/cloud/ingest/test_ratelimit.py covers the limit). The schemathesis service runs with the default
limit, so its vehicle may meet 429s, which must conform too.
"""

from __future__ import annotations

import itertools
import json
import math
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import pytest
import schemathesis
from drives import patch_drive
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    ignored_auth,
    negative_data_rejection,
    response_headers_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mqtt import errors_topic
from roadgrip.data.schema import TELEMETRY, TELEMETRY_COLUMNS
from roadgrip.data.telemetry import RANGES
from roadgrip.fleet.terminal import wire_samples

SCHEMA_EXAMPLES = 60
INGEST_EXAMPLES = 600
MQTT_EXAMPLES = 800

ADMIN = ("admin", "admin-secret-for-tests-0123456789")
VEHICLE, READER = "fuzz-vehicle-7d41", "fuzz-reader-7d41"
INGEST_VEHICLE, MQTT_VEHICLE = "fuzz-ingest", "fuzz-mqtt"
START_MS = int(time.time() * 1000) - 3_600_000  # an hour ago: inside max_future_s
BLOCK_MS = 32  # each example's samples get timestamps of their own: BLOCK_MS apart, 1 ms between samples
MAX_SAMPLES = 12
STORED_WITHIN_S = 60.0  # a storage thread on a loaded machine; only a lost acknowledgement waits this long
JSON_TYPE, NDJSON_TYPE = "application/json", "application/x-ndjson"


def fuzz(max_examples: int) -> settings:
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,  # the same cases on every run: CI has no example database, and a landing may not hang on luck
        suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
    )


def _openapi() -> dict:
    """Our OpenAPI document (the routes do not depend on a running service)."""
    with tempfile.TemporaryDirectory() as tmp:
        return create_app(CloudService(Settings(data_dir=Path(tmp), mqtt="off"))).openapi()


OPERATIONS = [(method.upper(), path) for path, methods in _openapi()["paths"].items() for method in methods]
MODES = [schemathesis.GenerationMode.POSITIVE, schemathesis.GenerationMode.NEGATIVE]
ROLES = ["admin", "vehicle", "reader", "nobody"]
CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
    response_headers_conformance,
    ignored_auth,
    negative_data_rejection,
]


@dataclass
class Api:
    schema: schemathesis.BaseSchema  # read from the app's /openapi.json; calls go to the app
    auth: dict[str, tuple[str, str]]  # by role


def _serve(data_dir: Path, **overrides):
    settings_ = Settings(data_dir=data_dir, mqtt="off", admin_secret=ADMIN[1], map_clock="data", **overrides)
    return CloudService(settings_)


def _register(client: TestClient, vehicle_id: str) -> tuple[str, str]:
    answer = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id}, auth=ADMIN)
    assert answer.status_code == 201, answer.text
    return vehicle_id, answer.json()["secret"]


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    """The service as deployed (default rate limit), with a vehicle that drove over a slippery patch (estimates and a
    map to read) and a reader."""
    service = _serve(tmp_path_factory.mktemp("api"), flush_interval_s=0.01, reorder_window_s=0.05)
    with service, TestClient(app := create_app(service)) as client:
        vehicle = _register(client, VEHICLE)
        samples = wire_samples(patch_drive(0.2, 1), VEHICLE, START_MS)
        for k in range(0, len(samples), 50):
            assert client.post("/v1/telemetry", json=samples[k : k + 50], auth=vehicle).status_code == 200
        reader = client.post("/v1/readers", json={"name": READER}, auth=ADMIN).json()
        _wait_for(lambda: service.storage.counts()["estimates"] == len(samples), "the drive's estimates")
        yield Api(
            schemathesis.openapi.from_asgi("/openapi.json", app),
            {"admin": ADMIN, "vehicle": vehicle, "reader": (READER, reader["secret"])},
        )


def _wait_for(predicate, what: str, timeout_s: float = 20.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, f"{what}: not within {timeout_s} s"
        time.sleep(0.02)


@pytest.mark.slow  # 88 cases of 60 requests: over a minute in all, most of it outside the fast subset
@pytest.mark.parametrize("role", ROLES)
@pytest.mark.parametrize("mode", MODES, ids=[m.value for m in MODES])
@pytest.mark.parametrize("operation", OPERATIONS, ids=[f"{m} {p}" for m, p in OPERATIONS])
@fuzz(SCHEMA_EXAMPLES)
@given(data=st.data())
def test_every_operation_answers_generated_requests_as_its_openapi_says(api, operation, mode, role, data):
    method, path = operation
    operation_ = api.schema[path][method]
    strategy = operation_.as_strategy(generation_mode=mode)
    if role == "vehicle" and "{vehicle_id}" in path:  # its own vehicle too, not only ids it may not read
        strategy |= operation_.as_strategy(generation_mode=mode, path_parameters={"vehicle_id": VEHICLE})
    case = data.draw(strategy)
    assume((case.path_parameters or {}).get("name") not in (VEHICLE, READER))  # the fuzzers' own credentials stay
    auth = {} if role == "nobody" else {"auth": api.auth[role]}
    case.call_and_validate(checks=CHECKS, **auth)


# ------------------------------------------------------------------------------------------------ ingest: strategies

# Any character, lone surrogates included (JSON's \\u escapes carry them; hypothesis leaves them out by default), and
# more often those that broke something once or that quoting must survive.
HOSTILE_CHARACTERS = ["\x00", "\ud800", "\udfff", "\u2028", "\ufeff", "'", '"', "\\", "\n", "\r", "%", ";"]


def texts(max_size: int) -> st.SearchStrategy[str]:
    # joined lists, not st.text: st.text drops lone surrogates whatever its alphabet
    return st.lists(st.characters(exclude_categories=()) | st.sampled_from(HOSTILE_CHARACTERS), max_size=max_size).map(
        "".join
    )


any_text = texts(20)
any_bytes = st.binary(max_size=300) | texts(300).map(lambda t: t.encode("utf-8", "surrogatepass"))
json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | any_text,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(any_text, inner, max_size=4),
    max_leaves=8,
)


@st.composite
def valid_samples(draw) -> dict:
    """A valid sample of wire format v1 (CONTRACTS 3.1) without vehicle_id and timestamp_ms (the test sets them): every
    number inside its physical range, optional fields present, null or absent."""
    out = {}
    for c in TELEMETRY:
        if c.name in ("vehicle_id", "timestamp_ms"):
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


mutations = st.tuples(st.sampled_from(TELEMETRY_COLUMNS) | any_text, json_values)
content_types = st.sampled_from(
    [None, JSON_TYPE, NDJSON_TYPE, "application/json; charset=utf-8", "text/plain"]
) | st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=30)  # what a header can carry
# UTF-8 text (one bad byte would refuse the whole body), JSON's pieces and escapes more often than by chance
junk_lines = st.lists(
    st.characters(codec="utf-8", exclude_characters="\n")
    | st.sampled_from(
        ["{", "}", "[", "]", ",", ":", '"', "\\ud800", "\\u0000", "NaN", "1e999", '{"vehicle_id": ']
        + HOSTILE_CHARACTERS[3:8]
    ),
    max_size=20,
).map("".join)

_blocks = itertools.count()


def fresh_block() -> int:
    """The first timestamp of a block of BLOCK_MS milliseconds that no other example uses."""
    return START_MS + BLOCK_MS * next(_blocks)


def stamped(vehicle_id: str, samples: list[dict], start_ms: int) -> list[dict]:
    return [{"vehicle_id": vehicle_id, "timestamp_ms": start_ms + k, **s} for k, s in enumerate(samples)]


def as_stored(sample: dict) -> dict:
    """A valid sample as the database returns it: every column, numbers as floats, absent optional fields null."""
    return {
        name: (float(sample[name]) if name in RANGES and sample.get(name) is not None else sample.get(name))
        for name in TELEMETRY_COLUMNS
    }


def encode(samples: list, fmt: str) -> tuple[bytes, str | None]:
    if fmt == "ndjson":
        return "\n".join(json.dumps(s) for s in samples).encode(), NDJSON_TYPE
    return json.dumps(samples).encode(), (JSON_TYPE if fmt == "json" else None)


def not_in_the_fuzzed_window(key: str, value) -> bool:
    """A mutated timestamp that could land in another example's block would blur that example's count."""
    return not (
        key == "timestamp_ms" and type(value) in (int, float) and not math.isnan(value) and value >= START_MS - 1
    )


# ------------------------------------------------------------------------------------------------ ingest: HTTP


@pytest.fixture(scope="module")
def ingest(tmp_path_factory):
    """A service with the rate limit off, a vehicle for HTTP ingest and one for MQTT."""
    with (
        _serve(
            tmp_path_factory.mktemp("ingest"), flush_interval_s=0.002, reorder_window_s=0.0, rate_limit_samples_per_s=0
        ) as service,
        TestClient(create_app(service)) as client,
    ):
        auth = _register(client, INGEST_VEHICLE)
        _register(client, MQTT_VEHICLE)
        yield service, client, auth


def rows(service: CloudService) -> int:
    return service.storage.counts()["telemetry"]  # one vehicle writes at a time in this service


def stored_in(service: CloudService, vehicle_id: str, start_ms: int) -> list[dict]:
    return service.storage.telemetry(vehicle_id, start_ms, start_ms + BLOCK_MS)


def post(ingest, body: bytes, content_type: str | None) -> tuple[set[int] | None, int]:
    """POST the body; check the answer's shape; (indices rejected, or None when the body was refused whole; rows
    the database gained)."""
    service, client, auth = ingest
    before = rows(service)
    answer = client.post(
        "/v1/telemetry", content=body, auth=auth, headers={} if content_type is None else {"content-type": content_type}
    )
    gained = rows(service) - before
    assert answer.status_code < 500, answer.text
    result = answer.json()
    if answer.status_code == 200 or (answer.status_code == 422 and "rejected" in result):
        assert result["received"] == result["accepted"] + len(result["rejected"])
        assert result["accepted"] == result["stored"] + result["duplicates"]
        assert (answer.status_code == 200) == (result["accepted"] > 0)
        for rejection in result["rejected"]:
            assert type(rejection["index"]) is int and 0 <= rejection["index"]
            assert rejection["field"] is None or type(rejection["field"]) is str  # the key as sent, "" included
            assert type(rejection["reason"]) is str and rejection["reason"].strip()
        indices = [r["index"] for r in result["rejected"]]
        assert len(set(indices)) == len(indices)
        assert gained == result["stored"]
        return set(indices), gained
    assert answer.status_code in (400, 413, 415), answer.text
    assert result["detail"]["reason"].strip()
    assert gained == 0
    return None, gained


@fuzz(INGEST_EXAMPLES)
@given(value=json_values, detect=st.booleans())
@pytest.mark.slow
def test_http_any_json_gets_clear_rejections_and_stores_only_what_it_says(ingest, value, detect):
    post(ingest, json.dumps(value).encode(), None if detect else JSON_TYPE)


@fuzz(INGEST_EXAMPLES)
@given(
    samples=st.lists(valid_samples(), max_size=MAX_SAMPLES - 1),
    bad=valid_samples(),
    mutation=mutations,
    data=st.data(),
    fmt=st.sampled_from(["json", "ndjson", "detect"]),
)
@pytest.mark.slow
def test_http_one_mutated_field_loses_no_valid_sample(ingest, samples, bad, mutation, data, fmt):
    key, value = mutation
    assume(not_in_the_fuzzed_window(key, value))
    start_ms = fresh_block()
    where = data.draw(st.integers(0, len(samples)))
    body_samples = stamped(INGEST_VEHICLE, samples[:where] + [bad] + samples[where:], start_ms)
    valid = [s for k, s in enumerate(body_samples) if k != where]
    body_samples[where][key] = value
    rejected, _ = post(ingest, *encode(body_samples, fmt))
    assert rejected is not None and rejected <= {where}
    service = ingest[0]
    mutant_kept = where not in rejected and body_samples[where]["timestamp_ms"] == start_ms + where
    expected = [as_stored(s) for s in valid] + ([as_stored(body_samples[where])] if mutant_kept else [])
    assert stored_in(service, INGEST_VEHICLE, start_ms) == sorted(expected, key=lambda s: s["timestamp_ms"])


@fuzz(INGEST_EXAMPLES)
@given(body=any_bytes, content_type=content_types)
@pytest.mark.slow
def test_http_any_bytes_never_give_a_server_error(ingest, body, content_type):
    post(ingest, body, content_type)


@fuzz(INGEST_EXAMPLES)
@given(
    lines=st.lists(
        valid_samples().map(lambda s: ("sample", s)) | junk_lines.map(lambda j: ("junk", j)),
        min_size=1,
        max_size=MAX_SAMPLES,
    )
)
@pytest.mark.slow
def test_http_ndjson_with_junk_lines_keeps_every_valid_line(ingest, lines):
    start_ms = fresh_block()
    text, valid, junk = [], [], set()
    for k, (kind, item) in enumerate(lines):
        if kind == "sample":
            (sample,) = stamped(INGEST_VEHICLE, [item], start_ms + k)
            valid.append(sample)
            text.append(json.dumps(sample))
        else:
            junk.add(k)
            text.append(item)
    rejected, _ = post(ingest, "\n".join(text).encode(), NDJSON_TYPE)
    if valid:
        assert rejected is not None and rejected <= junk
    assert stored_in(ingest[0], INGEST_VEHICLE, start_ms) == [as_stored(s) for s in valid]


# ------------------------------------------------------------------------------------------------ ingest: MQTT


class Ack:
    """A fake MQTT acknowledgement: counts its calls and the telemetry rows stored when it was first called."""

    def __init__(self, service: CloudService):
        self.service = service
        self.calls = 0
        self.rows_then: int | None = None
        self.done = threading.Event()

    def __call__(self) -> None:
        self.calls += 1
        if self.rows_then is None:
            self.rows_then = rows(self.service)
        self.done.set()


@pytest.fixture(scope="module")
def mqtt_handler(ingest):
    """Call the service's MQTT telemetry handler as paho would, recording what it submits to the pipeline and what it
    publishes. Yields handle(payload) -> (ack, submitted samples, published error reports)."""
    service = ingest[0]
    submit, publish = service.ingest.pipeline.submit, service._publish
    submitted, published = [], []

    def recording_submit(vehicle_id, samples, **options):
        future = submit(vehicle_id, samples, **options)
        submitted.append((vehicle_id, samples, future))
        return future

    service.ingest.pipeline.submit = recording_submit
    service._publish = lambda topic, payload: published.append((topic, payload))

    def handle(payload: bytes) -> tuple[Ack, list[dict], list[dict]]:
        submitted.clear()
        published.clear()
        ack = Ack(service)
        before = rows(service)
        service.ingest.mqtt_message(MQTT_VEHICLE, payload, ack)  # must not raise
        reports = []
        for topic, body in published:
            assert topic == errors_topic(MQTT_VEHICLE)
            report = json.loads(body)
            assert report["vehicle_id"] == MQTT_VEHICLE and report["rejected"]
            for rejection in report["rejected"]:
                assert rejection["index"] is None or type(rejection["index"]) is int  # None: the whole message
                assert rejection["field"] is None or type(rejection["field"]) is str
                assert type(rejection["reason"]) is str and rejection["reason"].strip()
            reports += report["rejected"]
        samples = [s for vehicle_id, batch, _ in submitted for s in batch]
        assert all(vehicle_id == MQTT_VEHICLE for vehicle_id, _, _ in submitted)
        assert samples or reports, "a message neither queued nor refused"
        if not submitted:
            assert ack.calls == 1, "a message without a valid sample must be acknowledged at once"
            assert rows(service) == before
        else:
            ((_, _, future),) = submitted
            finished = threading.Event()
            future.add_done_callback(lambda _: finished.set())  # runs after the service's own callback (the ack)
            assert finished.wait(STORED_WITHIN_S) and ack.done.is_set(), "no acknowledgement after storage"
            assert ack.calls == 1
            assert ack.rows_then == rows(service), "acknowledged before its samples were stored"
            assert ack.rows_then - before == future.result().stored
        return ack, samples, reports

    yield handle
    service.ingest.pipeline.submit, service._publish = submit, publish


@fuzz(MQTT_EXAMPLES)
@given(value=json_values)
@pytest.mark.slow
def test_mqtt_any_json_is_refused_clearly_and_acknowledged_once(mqtt_handler, value):
    mqtt_handler(json.dumps(value).encode())


@fuzz(MQTT_EXAMPLES)
@given(
    samples=st.lists(valid_samples(), max_size=MAX_SAMPLES - 1),
    bad=valid_samples(),
    mutation=mutations,
    data=st.data(),
    ndjson=st.booleans(),
)
@pytest.mark.slow
def test_mqtt_one_mutated_field_loses_no_valid_sample(ingest, mqtt_handler, samples, bad, mutation, data, ndjson):
    key, value = mutation
    assume(not_in_the_fuzzed_window(key, value))
    start_ms = fresh_block()
    where = data.draw(st.integers(0, len(samples)))
    body_samples = stamped(MQTT_VEHICLE, samples[:where] + [bad] + samples[where:], start_ms)
    valid = [s for k, s in enumerate(body_samples) if k != where]
    body_samples[where][key] = value
    _, _, reports = mqtt_handler(encode(body_samples, "ndjson" if ndjson else "detect")[0])
    rejected = {r["index"] for r in reports}
    assert rejected <= {where}
    mutant_kept = where not in rejected and body_samples[where]["timestamp_ms"] == start_ms + where
    expected = [as_stored(s) for s in valid] + ([as_stored(body_samples[where])] if mutant_kept else [])
    assert stored_in(ingest[0], MQTT_VEHICLE, start_ms) == sorted(expected, key=lambda s: s["timestamp_ms"])


@fuzz(MQTT_EXAMPLES)
@given(payload=any_bytes)
@pytest.mark.slow
def test_mqtt_any_bytes_are_refused_clearly_and_acknowledged_once(mqtt_handler, payload):
    mqtt_handler(payload)
