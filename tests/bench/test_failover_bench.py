"""The failover count's arithmetic (roadgrip/bench/failover.py) on polls of known shape; the run itself is
`roadgrip bench failover` (docs/RELIABILITY.md)."""

import pytest

from roadgrip.bench.failover import FailoverBench, _longest_stall, _resumed

# (wall time, {vehicle: (stored rows, newest timestamp_ms)}): rows grow at 1, 2 and 9 s; nothing from 2 to 9 s
POLLS = [
    (t, {"v": (n, newest)})
    for t, n, newest in [
        (0.0, 0, 0),
        (1.0, 5, 900),
        (2.0, 9, 1_900),
        (5.0, 9, 1_900),
        (9.0, 14, 8_900),
        (10.0, 14, 8_900),
    ]
]


def test_the_longest_stall_is_the_longest_wall_time_without_a_new_row():
    assert _longest_stall(POLLS, "v", 0.0, 10.0) == pytest.approx(7.0)
    assert _longest_stall(POLLS, "v", 0.0, 4.0) == pytest.approx(2.0)  # the window ends inside the stall
    assert _longest_stall(POLLS, "other", 0.0, 10.0) == pytest.approx(10.0)  # never stored anything


def test_a_vehicle_resumes_when_a_sample_produced_after_the_kill_is_stored():
    assert _resumed(POLLS, "v", 3.0) == pytest.approx(6.0)  # 8,900 ms is the first sample after 3 s
    assert _resumed(POLLS, "v", 9.5) is None


def test_the_faults_must_come_in_order_within_the_drive():
    with pytest.raises(ValueError, match="worker_kill_s < node_kill_s"):
        FailoverBench(node_kill_s=70.0, node_restart_s=60.0)
    with pytest.raises(ValueError, match="node must be 0, 1 or 2"):
        FailoverBench(node=3)
