"""The spreading rule (roadgrip/cloud/cluster/spread.py) on its own: shares, settling, the move interval, ties."""

from __future__ import annotations

import pytest

from roadgrip.cloud.cluster.spread import WORKERS_SETTLE_S, Spread


def settled(spread: Spread, workers: int) -> float:
    """Let the rule see `workers` live workers long enough to move; the time it is then."""
    assert spread.release(0.0, workers, {}, dict) is None
    return WORKERS_SETTLE_S


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
    assert spread.release(0.0, 2, held, no_owners) is None
    assert spread.release(WORKERS_SETTLE_S - 0.1, 2, held, no_owners) is None
    assert spread.release(WORKERS_SETTLE_S, 2, held, no_owners) == 3
    held.pop(3)  # released; 3 is still more than ceil(4 / 2)
    assert spread.release(WORKERS_SETTLE_S + 2.9, 2, held, no_owners) is None  # within the move interval
    assert spread.release(WORKERS_SETTLE_S + 3.0, 2, held, no_owners) == 2
    held.pop(2)
    assert spread.release(WORKERS_SETTLE_S + 6.0, 1, held, no_owners) is None  # the count changed: settle again
    assert spread.release(2 * WORKERS_SETTLE_S + 6.0, 1, {0: 0.0, 1: 1.0, 2: 2.0}, no_owners) is None  # 3 of 4: ok


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
