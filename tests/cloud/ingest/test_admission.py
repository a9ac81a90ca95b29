"""The waiting line of the processes that read a broker (`WaitingLine`): what the pipeline refuses (Busy) waits, in
the broker's order, and is handed over once, when the pipeline has room again."""

from __future__ import annotations

from roadgrip.cloud.ingest.admission import WaitingLine


class Pipeline:
    """A pipeline that takes `capacity` deliveries, then refuses (Busy) until the test works some off."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self.taken: list[int] = []
        self.worked = 0

    def hand(self, delivery: int) -> bool:
        if len(self.taken) - self.worked >= self.capacity:
            return False
        self.taken.append(delivery)
        return True

    def has_room(self) -> bool:
        return len(self.taken) - self.worked <= self.capacity // 2


def test_refused_deliveries_wait_in_order_and_each_is_handed_over_once():
    pipeline = Pipeline(capacity=4)
    line = WaitingLine(pipeline.has_room, pipeline.hand)
    for delivery in range(10):
        line.offer(delivery)
    assert pipeline.taken == [0, 1, 2, 3] and len(line) == 6
    pipeline.worked = 2  # room for two again, yet a new delivery waits behind the earlier ones
    line.offer(10)
    assert pipeline.taken == [0, 1, 2, 3] and len(line) == 7
    while line:
        line.drain()
        pipeline.worked = len(pipeline.taken)
    assert pipeline.taken == list(range(11))


def test_nothing_is_handed_over_until_the_pipeline_has_room_again():
    pipeline = Pipeline(capacity=4)
    line = WaitingLine(pipeline.has_room, pipeline.hand)
    for delivery in range(6):
        line.offer(delivery)
    pipeline.worked = 1  # the pipeline would take one more, but its backlog is above half its bound
    line.drain()
    assert pipeline.taken == [0, 1, 2, 3] and len(line) == 2
    pipeline.worked = 2
    line.drain()
    assert pipeline.taken == [0, 1, 2, 3, 4, 5] and not line
