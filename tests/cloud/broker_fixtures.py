"""A real Mosquitto for the MQTT tests (imported by test_broker.py and test_mqtt.py; to move to conftest.py later).

- `managed_broker`: a `ManagedBroker` on 127.0.0.1 at a free port, in the test's tmp_path, stopped after the test. Without
  mosquitto the fixture fails (it never skips): the broker's behaviour is what these tests check.
- `Inbox`: an `on_telemetry` handler that records what arrives, acknowledging it unless told not to.
- `wait_until(predicate)`: poll until true or fail.
"""

from __future__ import annotations

import queue
import time

import pytest

from roadgrip.cloud.transport.mosquitto import INSTALL_HINT, ManagedBroker, mosquitto_available


@pytest.fixture
def managed_broker(tmp_path):
    if not mosquitto_available():
        pytest.fail(f"mosquitto is not installed: {INSTALL_HINT}", pytrace=False)
    broker = ManagedBroker(tmp_path / "mosquitto")
    broker.start()
    yield broker
    broker.stop()


class Inbox:
    """Records (vehicle_id, payload, ack) of each telemetry message; calls ack at once when `auto_ack`."""

    def __init__(self, auto_ack: bool = True):
        self.auto_ack = auto_ack
        self._queue: queue.Queue = queue.Queue()

    def __call__(self, vehicle_id: str, payload: bytes, ack) -> None:
        if self.auto_ack:
            ack()
        self._queue.put((vehicle_id, payload, ack))

    def take(self, n: int, timeout_s: float = 5) -> list[tuple]:
        """The next `n` messages; fails the test when they do not come within `timeout_s`."""
        deadline = time.monotonic() + timeout_s
        got = []
        while len(got) < n:
            try:
                got.append(self._queue.get(timeout=max(0.0, deadline - time.monotonic())))
            except queue.Empty:
                pytest.fail(f"{len(got)} of {n} messages arrived within {timeout_s} s: {got}")
        return got

    def payloads(self, n: int, timeout_s: float = 5) -> list[tuple[str, bytes]]:
        return [(vid, payload) for vid, payload, _ in self.take(n, timeout_s)]

    def empty(self) -> bool:
        return self._queue.empty()


def wait_until(predicate, timeout_s: float = 5, what: str = "condition") -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            pytest.fail(f"{what} not reached within {timeout_s} s")
        time.sleep(0.01)
