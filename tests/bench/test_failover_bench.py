"""The failover count's arithmetic (roadgrip/bench/failover.py) on polls of known shape; the run itself is
`roadgrip bench failover` (docs/RELIABILITY.md)."""

from datetime import datetime

import pytest

from roadgrip.bench.failover import FailoverBench, _longest_stall, _resumed, count_moves, read_worker_logs

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


def log_line(t_s: float, logger: str, message: str) -> str:
    """A line as `roadgrip worker` logs it (roadgrip/cli/cloud.py's format), at local time t_s (time.time() s)."""
    stamp = datetime.fromtimestamp(t_s).strftime("%Y-%m-%d %H:%M:%S,%f")[:-3]
    return f"{stamp} INFO roadgrip.cloud.cluster.{logger}: {message}"


T0 = 1_800_000_000.0  # the drive's start
KILL = T0 + 30.0


def worker_logs(tmp_path, survivor_after_kill: list[tuple[float, str, str]]) -> dict[str, list[dict]]:
    """Worker 0 takes the four partitions at the drive's start and releases 3 and 2 to worker 1 before the kill;
    worker 1 counts 1 live worker from 10 s after it; `survivor_after_kill`: more of worker 1's lines."""
    w0 = [
        "2026-12-03 10:00:00,000 INFO roadgrip.cloud.cluster.worker: partition 0 taken, epoch 1",  # before the drive
        *[log_line(T0 + 0.5, "worker", f"partition {p} taken, epoch {p + 1}") for p in range(4)],
        log_line(T0 + 0.6, "regions", "region queue 1 taken, epoch 1"),  # a region queue: not a partition
        log_line(T0 + 15.5, "spread", "releasing partition 3: this worker holds 4 of 4 partitions, more than ..."),
        log_line(T0 + 16.0, "worker", "partition 3 released: 41 deliveries stored and acknowledged, the states ..."),
        log_line(T0 + 17.5, "worker", "partition 2 released: 30 deliveries stored and acknowledged, the states ..."),
        "Traceback (most recent call last):",
    ]
    w1 = [
        log_line(T0 + 16.1, "worker", "partition 3 taken, epoch 5"),
        log_line(T0 + 17.6, "worker", "partition 2 taken, epoch 4"),
        log_line(KILL + 0.1, "worker", "partition 0 taken, epoch 2"),
        log_line(KILL + 0.1, "worker", "partition 1 taken, epoch 3"),
        log_line(KILL + 10.2, "spread", "live workers: 1"),
        log_line(KILL + 10.2, "spread", "live workers: 1"),  # the region queues' rule says it too
        *[log_line(KILL + dt, logger, message) for dt, logger, message in survivor_after_kill],
    ]
    paths = {}
    for name, lines in (("worker-0", w0), ("worker-1", w1)):
        path = tmp_path / f"{name}.log"
        path.write_text("\n".join(lines) + "\n")
        paths[path] = len(lines[0]) + 1 if name == "worker-0" else 0  # worker 0's first line came before the drive
    return read_worker_logs(paths)


def test_moves_counted_from_the_workers_log_lines(tmp_path):
    node_kill = [
        (
            20.0,
            "worker",
            "partition 0: connection through broker 0 lost (ConnectionResetError()); forgetting its 5 vehicles",
        ),
        (20.3, "worker", "partition 0 taken, epoch 3"),  # the same worker again, through another node: no move
    ]
    moves = count_moves(worker_logs(tmp_path, node_kill), {"worker_kill": KILL}, partitions=4, workers=2)
    assert moves == {
        "takes": 9,
        "retakes_by_the_same_worker": 1,
        "owner_changes": 4,  # 3 and 2 released, 0 and 1 taken over from the dead worker
        "owner_changes_from_worker_kill": 2,
        "released_before_worker_kill": 2,
        "released_from_worker_kill": 0,
        "lost_connections": 1,
        "live_workers_seen": {"worker-0": [], "worker-1": [1]},
        "within_target": True,
    }


def test_a_survivor_that_thrashes_misses_the_target(tmp_path):
    thrash = [
        (dt, logger, message)
        for k, dt in enumerate((21.0, 22.5))
        for logger, message in (
            ("spread", "live workers: 2"),
            ("worker", "partition 1 released: 12 deliveries stored and acknowledged, the states of 5 vehicles ..."),
            ("worker", f"partition 1 taken, epoch {4 + k}"),
        )
    ]
    moves = count_moves(worker_logs(tmp_path, thrash), {"worker_kill": KILL}, partitions=4, workers=2)
    assert moves["released_from_worker_kill"] == 2 and not moves["within_target"]
    assert moves["live_workers_seen"]["worker-1"] == [1, 2]
