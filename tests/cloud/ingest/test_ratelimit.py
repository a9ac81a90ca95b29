"""The per-vehicle rate limit (roadgrip/cloud/ingest/ratelimit.py): a token bucket per vehicle on a fake clock, its thread
safety, and HTTP ingest over it (a vehicle far above the rate gets 429, nothing of it stored, and another vehicle goes
on)."""

from __future__ import annotations

import json
import math
import threading
import time

import pytest
from drives import patch_drive
from fastapi.testclient import TestClient

from roadgrip.cloud.api.app import create_app
from roadgrip.cloud.ingest.ratelimit import RateLimiter
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.transport.mqtt import errors_topic
from roadgrip.fleet.terminal import wire_samples

ADMIN = ("admin", "admin-secret-for-tests-0123456789")
START_MS = int(time.time() * 1000) - 3_600_000


def test_a_new_vehicle_may_send_its_burst_at_once_then_no_more():
    limiter = RateLimiter(samples_per_s=50.0, burst_s=10.0)
    assert limiter.burst == 500
    assert limiter.allow("car-1", 300, now_s=0.0).allowed
    assert limiter.allow("car-1", 200, now_s=0.0).allowed
    refused = limiter.allow("car-1", 1, now_s=0.0)
    assert not refused.allowed
    assert refused.retry_after_s == pytest.approx(1 / 50)
    assert "car-1" in refused.reason and "50 samples/s" in refused.reason and "retry in" in refused.reason


def test_the_bucket_refills_at_the_rate_and_no_higher_than_the_burst():
    limiter = RateLimiter(samples_per_s=10.0, burst_s=2.0)  # 20 samples; times in binary fractions: exact sums
    assert limiter.allow("car-1", 20, now_s=100.0).allowed
    assert not limiter.allow("car-1", 5, now_s=100.25).allowed  # 2.5 back
    assert limiter.allow("car-1", 5, now_s=100.5).allowed  # 5 back
    assert limiter.allow("car-1", 0, now_s=100.5).allowed
    waited = limiter.allow("car-1", 10, now_s=100.5)
    assert not waited.allowed and waited.retry_after_s == pytest.approx(1.0)
    assert limiter.allow("car-1", 10, now_s=100.5 + waited.retry_after_s).allowed  # the promised wait is enough
    assert limiter.allow("car-1", 20, now_s=1_000.0).allowed  # a long pause gives the burst, not more
    assert not limiter.allow("car-1", 1, now_s=1_000.0).allowed


def test_a_refused_message_takes_nothing_from_the_bucket():
    limiter = RateLimiter(samples_per_s=10.0, burst_s=1.0)
    assert limiter.allow("car-1", 8, now_s=0.0).allowed
    for _ in range(100):
        assert not limiter.allow("car-1", 5, now_s=0.0).allowed
    assert limiter.allow("car-1", 2, now_s=0.0).allowed


def test_over_any_interval_a_vehicle_gets_at_most_the_burst_plus_the_rate_times_the_interval():
    rate, burst_s = 50.0, 10.0
    limiter = RateLimiter(rate, burst_s)
    passed, t = 0, 0.0
    while t < 60.0:  # a terminal that sends 10 samples every 20 ms: 10 times the rate
        passed += 10 if limiter.allow("car-1", 10, t).allowed else 0
        t += 0.02
    assert rate * burst_s + rate * 60.0 - 10 <= passed <= rate * burst_s + rate * 60.0


def test_a_message_larger_than_the_burst_never_passes_and_says_so():
    limiter = RateLimiter(samples_per_s=50.0, burst_s=10.0)
    refused = limiter.allow("car-1", 501, now_s=0.0)
    assert not refused.allowed and refused.retry_after_s == math.inf
    assert "send at most 500 a message" in refused.reason
    assert limiter.allow("car-1", 500, now_s=0.0).allowed  # it took nothing


def test_vehicles_have_buckets_of_their_own():
    limiter = RateLimiter(samples_per_s=1.0, burst_s=5.0)
    assert limiter.allow("car-1", 5, now_s=0.0).allowed
    assert not limiter.allow("car-1", 1, now_s=0.0).allowed
    assert limiter.allow("car-2", 5, now_s=0.0).allowed
    assert not limiter.allow("car-2", 1, now_s=0.0).allowed


def test_idle_vehicles_are_forgotten_and_come_back_with_a_full_bucket():
    limiter = RateLimiter(samples_per_s=1.0, burst_s=5.0)
    for k in range(1000):
        assert limiter.allow(f"car-{k}", 1, now_s=k * 0.001).allowed
    assert limiter.tracked == 1000
    assert limiter.allow("car-new", 1, now_s=5.5).allowed  # 5 s after the first 500: they are full again
    assert limiter.tracked == 500
    assert limiter.allow("car-new", 1, now_s=100.0).allowed
    assert limiter.tracked == 1
    assert limiter.allow("car-1", 5, now_s=100.0).allowed  # forgotten: a full bucket, as if new


def test_memory_stays_bounded_by_the_vehicles_of_the_last_burst():
    limiter = RateLimiter(samples_per_s=10.0, burst_s=1.0)
    for k in range(100_000):  # a new vehicle every ms: only one burst_s of them is remembered
        limiter.allow(f"car-{k}", 1, now_s=k * 0.001)
        assert limiter.tracked <= 1001


def test_a_clock_that_goes_back_refills_nothing():
    limiter = RateLimiter(samples_per_s=10.0, burst_s=1.0)
    assert limiter.allow("car-1", 10, now_s=50.0).allowed
    assert not limiter.allow("car-1", 1, now_s=10.0).allowed
    assert limiter.allow("car-1", 1, now_s=50.1).allowed


def test_rate_zero_is_no_limit_and_bad_arguments_are_refused():
    limiter = RateLimiter(samples_per_s=0.0, burst_s=10.0)
    assert not limiter.enabled
    assert all(limiter.allow("car-1", 10_000, now_s=0.0).allowed for _ in range(100))
    assert limiter.tracked == 0
    for kwargs, name in (
        ({"samples_per_s": -1.0}, "samples_per_s"),
        ({"samples_per_s": math.nan}, "samples_per_s"),
        ({"burst_s": 0.0}, "burst_s"),
        ({"burst_s": math.inf}, "burst_s"),
    ):
        with pytest.raises(ValueError, match=name):
            RateLimiter(**kwargs)
    for n in (-1, 1.5, True):
        with pytest.raises(ValueError, match="n must be"):
            RateLimiter().allow("car-1", n, now_s=0.0)


def test_threads_together_get_exactly_the_burst():
    limiter = RateLimiter(samples_per_s=1.0, burst_s=1000.0)  # the clock stands still: 1000 samples, no refill
    passed = []
    start = threading.Barrier(8)

    def hammer():
        start.wait()
        passed.append(sum(limiter.allow("car-1", 1, now_s=0.0).allowed for _ in range(500)))

    threads = [threading.Thread(target=hammer) for _ in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert sum(passed) == 1000


def test_the_settings_carry_the_limit():
    settings = Settings()
    assert (settings.rate_limit_samples_per_s, settings.rate_limit_burst_s) == (50.0, 10.0)
    with pytest.raises(ValueError):
        Settings(rate_limit_samples_per_s=-1.0)


# ------------------------------------------------------------------------------------------------ over HTTP


@pytest.fixture
def cloud(tmp_path):
    settings = Settings(
        data_dir=tmp_path,
        mqtt="off",
        admin_secret=ADMIN[1],
        flush_interval_s=0.01,
        rate_limit_samples_per_s=10.0,
        rate_limit_burst_s=5.0,
    )  # 50 samples of burst
    with CloudService(settings) as service, TestClient(create_app(service)) as client:
        yield service, client


def _register(client, vehicle_id):
    answer = client.post("/v1/vehicles", json={"vehicle_id": vehicle_id}, auth=ADMIN)
    assert answer.status_code == 201
    return vehicle_id, answer.json()["secret"]


def test_a_vehicle_far_above_the_rate_gets_429_and_another_vehicle_is_unaffected(cloud):
    service, client = cloud
    greedy, modest = _register(client, "greedy"), _register(client, "modest")
    greedy_samples = wire_samples(patch_drive(0.9, 3), "greedy", START_MS)
    modest_samples = wire_samples(patch_drive(0.9, 3), "modest", START_MS)
    answers = [client.post("/v1/telemetry", json=greedy_samples[k : k + 10], auth=greedy) for k in range(0, 200, 10)]
    codes = [a.status_code for a in answers]
    assert codes[:5] == [200] * 5  # the burst: 50 samples
    assert codes.count(429) >= 14  # then refill at 10 samples/s, while 150 are sent within a moment
    refused = next(a for a in answers if a.status_code == 429)
    assert 1 <= int(refused.headers["Retry-After"]) <= 2
    assert "rate limit" in refused.json()["detail"] and "greedy" in refused.json()["detail"]
    stored = {row["timestamp_ms"] for row in service.storage.telemetry("greedy")}
    accepted = {
        s["timestamp_ms"]
        for a, k in zip(answers, range(0, 200, 10))
        if a.status_code == 200
        for s in greedy_samples[k : k + 10]
    }
    assert stored == accepted  # the refused requests stored nothing
    for k in range(0, 50, 10):  # meanwhile the other vehicle has its whole burst
        assert client.post("/v1/telemetry", json=modest_samples[k : k + 10], auth=modest).status_code == 200
    too_big = client.post("/v1/telemetry", json=modest_samples[50:101], auth=modest)
    assert too_big.status_code == 413 and "send at most 50 a message" in too_big.json()["detail"]


def test_over_mqtt_a_refused_message_is_reported_and_acknowledged_and_http_and_mqtt_share_the_bucket(cloud):
    """One limiter (Ingest.rate_limiter) for HTTP and MQTT, checked in Ingest.submit."""
    service, client = cloud
    vehicle = _register(client, "mqtt-car")
    samples = wire_samples(patch_drive(0.9, 3), "mqtt-car", START_MS)
    assert client.post("/v1/telemetry", json=samples[:50], auth=vehicle).status_code == 200  # the whole burst
    published, acks = [], []
    service._publish = lambda topic, payload: published.append((topic, json.loads(payload)))
    service.ingest.mqtt_message("mqtt-car", json.dumps(samples[50:60]).encode(), lambda: acks.append("ack"))
    assert acks == ["ack"]  # at once: a refused message must not come back from the broker
    ((topic, report),) = published
    assert topic == errors_topic("mqtt-car") and report["vehicle_id"] == "mqtt-car"
    assert "rate limit" in report["rejected"][0]["reason"]
    time.sleep(0.2)
    assert len(service.storage.telemetry("mqtt-car")) == 50
