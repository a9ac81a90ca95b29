"""The spreading rule (roadgrip/cloud/cluster/spread.py) on its own: shares, settling, the move interval, ties, a
queue that comes back; and who lives by the heartbeats (`Liveness`), on an injected clock."""

from __future__ import annotations

import pytest

from roadgrip.cloud.cluster.spread import DEAD_ROW_S, FRESH_S, WORKER_LEASE_S, WORKERS_SETTLE_S, Liveness, Spread

T0 = FRESH_S  # the queues below were taken at 0-4 s: from this time on they may move


def settled(spread: Spread, workers: int) -> float:
    """Let the rule see `workers` live workers long enough to move; the time it is then."""
    assert spread.release(T0, workers, {}, dict) is None
    return T0 + WORKERS_SETTLE_S


def no_owners():
    raise AssertionError("the owners are read only when the second rule needs them")


def test_more_than_ceil_releases_the_queue_taken_last():
    spread = Spread(4, "partition", "a", move_interval_s=1.0)
    now = settled(spread, 2)
    held = {0: 1.0, 1: 4.0, 2: 2.0, 3: 3.0}
    assert spread.release(now, 2, held, no_owners) == 1
    assert spread.moves == 1


def test_nothing_moves_before_the_count_of_workers_has_settled_nor_within_the_move_interval():
    spread = Spread(4, "partition", "a", move_interval_s=3.0)
    held = {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0}
    assert spread.release(T0, 2, held, no_owners) is None
    assert spread.release(T0 + WORKERS_SETTLE_S - 0.1, 2, held, no_owners) is None
    assert spread.release(T0 + WORKERS_SETTLE_S, 2, held, no_owners) == 3
    held.pop(3)  # released; 3 is still more than ceil(4 / 2)
    assert spread.release(T0 + WORKERS_SETTLE_S + 2.9, 2, held, no_owners) is None  # within the move interval
    assert spread.release(T0 + WORKERS_SETTLE_S + 3.0, 2, held, no_owners) == 2
    held.pop(2)
    assert spread.release(T0 + WORKERS_SETTLE_S + 6.0, 1, held, no_owners) is None  # the count changed: settle again
    assert spread.release(T0 + 2 * WORKERS_SETTLE_S + 6.0, 1, {0: 0.0, 1: 1.0, 2: 2.0}, no_owners) is None  # 3 of 4


def test_a_queue_taken_lately_stays_it_may_come_from_a_worker_whose_death_the_count_does_not_show_yet():
    spread = Spread(4, "partition", "a", move_interval_s=1.0)
    now = settled(spread, 2)
    held = {0: 0.0, 1: 1.0, 2: now, 3: now}  # 2 and 3 handed over by the broker just now
    assert spread.release(now + FRESH_S - 0.1, 2, held, no_owners) is None
    assert spread.release(now + FRESH_S, 2, held, no_owners) in (2, 3)


def test_a_share_within_floor_and_ceil_stays():
    spread = Spread(4, "region queue", "a", move_interval_s=1.0)
    now = settled(spread, 3)
    assert spread.release(now, 3, {0: 0.0, 1: 1.0}, lambda: {0: "a", 1: "a", 2: "b", 3: "c"}) is None


@pytest.mark.parametrize(("me", "moves"), [("a", True), ("b", False)])
def test_an_idle_worker_gets_a_queue_from_the_smallest_named_of_those_holding_most(me, moves):
    spread = Spread(4, "partition", me, move_interval_s=1.0)
    now = settled(spread, 3)
    owners = {0: "a", 1: "a", 2: "b", 3: "b"}  # c, live, holds none
    held = {p: float(p) for p, o in owners.items() if o == me}
    assert (spread.release(now, 3, held, lambda: owners) is not None) is moves


def test_unknown_or_no_live_workers_move_nothing():
    spread = Spread(2, "partition", "a", move_interval_s=1.0)
    for workers in (None, 0):
        assert spread.release(0.0, workers, {0: 0.0, 1: 1.0}, no_owners) is None
        assert spread.release(100.0, workers, {0: 0.0, 1: 1.0}, no_owners) is None


def test_a_released_queue_that_comes_back_stops_the_moves_until_the_count_of_workers_changes():
    """The issue-25 thrash: a worker that counts 2 live workers while no other takes what it releases would release
    the same partition every second; it releases it once, and then nothing until the count changes."""
    spread = Spread(4, "partition", "a", move_interval_s=1.0)
    now = settled(spread, 2)
    held = {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0}
    assert spread.release(now, 2, held, no_owners) == 3
    back = {**held, 3: now + 0.5}  # no one took it: it came back
    assert [spread.release(now + t, 2, back, no_owners) for t in range(1, 60)] == [None] * 59
    assert spread.moves == 1
    spread.release(now + 60, 3, back, no_owners)  # a worker joins: the count changed
    later = now + 60 + WORKERS_SETTLE_S
    assert spread.release(later, 3, back, no_owners) == 3  # more than ceil(4 / 3): moves again, once
    assert spread.moves == 2


def test_a_worker_that_stops_beating_is_dead_after_the_lease_and_one_that_stops_cleanly_at_once():
    liveness = Liveness()
    beats = {"a": 0, "b": 0, "c": 0}
    t = 0.0
    assert liveness.count(t, beats) == 3  # first seen: live for a lease
    while t < 3 * WORKER_LEASE_S:  # a and b beat every second; c was killed at 0
        t += 1.0
        beats["a"] += 1
        beats["b"] += 1
        assert liveness.count(t, beats) == (3 if t < WORKER_LEASE_S else 2), t
    del beats["b"]  # b stopped cleanly: its counter deleted
    assert liveness.count(t + 1.0, {**beats, "a": beats["a"] + 1}) == 1


def test_a_late_beat_within_the_lease_keeps_a_worker_live():
    liveness = Liveness()
    assert liveness.count(0.0, {"a": 0}) == 1
    assert liveness.count(WORKER_LEASE_S - 0.1, {"a": 0}) == 1  # a slow beat: still within the lease
    assert liveness.count(WORKER_LEASE_S - 0.05, {"a": 1}) == 1  # it came: a new lease from here
    assert liveness.count(2 * WORKER_LEASE_S - 0.1, {"a": 1}) == 1
    assert liveness.count(2 * WORKER_LEASE_S, {"a": 1}) == 0


def test_heartbeats_drive_at_most_one_move_per_real_change_and_a_flap_moves_nothing():
    """A worker holding 4 partitions, clock injected, beats read every second. b joins: after the settle time, a
    releases its excess (2 moves for that one change); b's beats pause for less than a lease (a flap in the database
    read, a stalled process): no count change, nothing moves; b is killed: a lease later the count is 1, and a
    moves nothing (it may hold all 4)."""
    liveness = Liveness()
    spread = Spread(4, "partition", "a", move_interval_s=1.0)
    held = {0: 0.0, 1: 1.0, 2: 2.0, 3: 3.0}
    beats = {"a": 0}
    moves_at: list[float] = []

    def second(t: float, b_beats: bool) -> None:
        beats["a"] += 1
        if b_beats:
            beats["b"] = beats.get("b", -1) + 1
        queue = spread.release(t, liveness.count(t, beats), held, no_owners)
        if queue is not None:
            held.pop(queue)
            moves_at.append(t)

    for t in range(10):
        second(float(t), b_beats=False)
    for t in range(10, 30):
        second(float(t), b_beats=True)
    assert len(moves_at) == 2 and moves_at[0] >= 10 + WORKERS_SETTLE_S  # 4 of 4 to 2 of 4, after the settle
    for t in range(30, 30 + int(WORKER_LEASE_S) - 2):  # b pauses for less than a lease
        second(float(t), b_beats=False)
    for t in range(38, 50):
        second(float(t), b_beats=True)
    assert len(moves_at) == 2
    held.update({2: 50.0, 3: 50.0})  # b is killed at 50: the broker gives a its partitions back
    for t in range(50, 100):
        second(float(t), b_beats=False)
    assert len(moves_at) == 2 and spread.moves == 2


def test_a_heartbeat_row_unmoved_for_long_is_named_for_deletion_with_its_count():
    liveness = Liveness()
    liveness.count(0.0, {"a": 5, "b": 7})
    liveness.count(DEAD_ROW_S, {"a": 6, "b": 7})
    assert liveness.dead_rows(DEAD_ROW_S) == {"b": 7}
