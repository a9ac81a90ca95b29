"""Where a cluster worker's CPU goes, end to end: `roadgrip bench cluster` (one worker case) with its `roadgrip worker`
process run under cProfile in every thread but the main one (which only starts the worker and waits), each thread's
profiler timed by that thread's CPU time (`time.thread_time`), so waiting in select() or on a lock costs nothing.
Only the bench's window is profiled (SIGUSR1 at its start clears, SIGUSR2 at its end writes the threads' profiles,
merged); this script then prints the CPU seconds by part and per sample stored in the window (the bench's count).
Another commit's worker: the same command with PYTHONPATH at an export of that commit.

cProfile inflates Python calls (a C builtin less so), so read the shares, not the seconds; run it under `nice -n 19`.

    nice -n 19 python results/trials/cluster/profile_worker.py --vehicles 500 --seconds 20 --out DIR
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import signal
import sys
import threading
import time
from pathlib import Path

# The parts of the worker, by the file a function is in (the first match of a frame's file wins; own time counted).
PARTS = (
    ("AMQP client (pika: frames, sockets, delivery, acks, publishes)", ("pika/",)),
    ("wire parse and checks (ingest)", ("roadgrip/cloud/ingest/",)),
    ("estimation (estimators, numba)", ("roadgrip/estimators/", "numba/")),
    (
        "pipeline (reorder, dedup, rounds)",
        ("roadgrip/cloud/pipeline/pipeline.py", "roadgrip/cloud/pipeline/checkpoints"),
    ),
    ("storage (SQLAlchemy, psycopg, COPY)", ("roadgrip/cloud/storage/", "sqlalchemy/", "psycopg")),
    (
        "region stage and friction topics (fan-out, map, warnings)",
        ("roadgrip/cloud/cluster/regions.py", "roadgrip/cloud/pipeline/fanout.py", "roadgrip/cloud/domain/"),
    ),
    ("JSON (orjson, json)", ("orjson", "json/")),
    ("h3", ("h3",)),
    ("worker's own (worker.py, amqp_client.py)", ("roadgrip/cloud/cluster/", "roadgrip/cloud/transport/")),
    ("threading, queues, logging", ("threading.py", "queue.py", "logging/")),
)


def _worker_main(out_dir: Path, argv: list[str]) -> None:
    """Run `roadgrip worker argv` with every new thread profiled by its own CPU time; write the merged profile."""
    profiles: list[cProfile.Profile] = []
    run = threading.Thread.run

    def profiled_run(self):
        profile = cProfile.Profile(time.thread_time)
        profiles.append(profile)
        profile.enable()
        try:
            run(self)
        finally:
            profile.disable()

    threading.Thread.run = profiled_run
    # the bench's window: SIGUSR1 at its start clears what the threads collected (start-up, warm-up), SIGUSR2 at its
    # end writes the profiles (the stop's checkpoints are left out)
    signal.signal(signal.SIGUSR1, lambda _s, _f: [p.clear() for p in list(profiles)])
    signal.signal(signal.SIGUSR2, lambda _s, _f: _dump(profiles, out_dir))
    from roadgrip.cli import app

    app(args=argv, prog_name="roadgrip", standalone_mode=False)


def _dump(profiles: list[cProfile.Profile], out_dir: Path) -> None:
    """Merge the threads' profiles as they stand (a snapshot: `create_stats` would disable them)."""
    stats = pstats.Stats()
    for profile in list(profiles):
        profile.snapshot_stats()
        one = pstats.Stats()
        one.stats = profile.stats
        one.get_top_level_stats()
        stats.add(one)
    stats.dump_stats(str(out_dir / f"worker-{os.getpid()}.prof"))


def part_of(filename: str) -> str:
    for name, needles in PARTS:
        if any(n in filename for n in needles):
            return name
    return "other (builtins, C calls not in a module above)"


def summarize(prof: Path, stored: int) -> dict:
    """Own CPU time by part; each C builtin's time goes to the part of its caller with most of its time."""
    stats = pstats.Stats(str(prof))
    by_part: dict[str, float] = {}
    for (filename, _line, name), (_cc, _nc, own_s, _cum_s, callers) in stats.stats.items():
        where = filename
        if filename == "~" and callers:  # a builtin: charged to its heaviest caller's file
            where = max(callers.items(), key=lambda kv: kv[1][2])[0][0]
        by_part[part_of(where)] = by_part.get(part_of(where), 0.0) + own_s
    total = sum(by_part.values())
    return {
        "profiled_cpu_s": total,
        "stored_samples": stored,
        "parts": {
            k: {"cpu_s": v, "share": v / total, "us_per_stored_sample": 1e6 * v / max(stored, 1)}
            for k, v in sorted(by_part.items(), key=lambda kv: -kv[1])
        },
    }


def main() -> None:
    if len(sys.argv) > 2 and sys.argv[1] == "--as-worker":
        _worker_main(Path(sys.argv[2]), sys.argv[3:])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vehicles", type=int, default=500)
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--partitions", type=int, default=8)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    out = args.out.resolve()
    wrapper = out / "roadgrip-profiled"
    wrapper.write_text(f'#!/bin/sh\nexec {sys.executable} {Path(__file__).resolve()} --as-worker {out} "$@"\n')
    wrapper.chmod(0o755)

    import roadgrip.bench.cluster as cluster_bench

    cluster_bench.ROADGRIP = wrapper
    logs: list[str] = []
    _Workers = cluster_bench._Workers

    class _KeptLogs(_Workers):  # the worker's log kept (DIR/worker.log); its processes noted for the signals
        def stop(self) -> None:
            super().stop()
            logs.extend(p.read_text() for p in self.logs)

        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            started.append(self)

    started: list[_KeptLogs] = []
    window = cluster_bench._window

    def signalled_window(*args, **kwargs):  # the worker case's window (the broker case has no workers)
        for workers in started:
            for proc in workers.procs:
                proc.send_signal(signal.SIGUSR1)
        try:
            return window(*args, **kwargs)
        finally:
            for workers in started:
                for proc in workers.procs:
                    proc.send_signal(signal.SIGUSR2)
            time.sleep(2.0)  # the dump

    cluster_bench._Workers = _KeptLogs
    cluster_bench._window = signalled_window
    bench = cluster_bench.ClusterBench(
        vehicles=args.vehicles, seconds=args.seconds, workers=(1,), partitions=args.partitions, rate=1.0
    )
    result = cluster_bench.run_cluster_bench(bench)
    (out / "bench.json").write_text(json.dumps(result, indent=1))
    (out / "worker.log").write_text("\n".join(logs))
    case = result["workers"][0]
    stored = round(case["stored_samples_per_s"] * case["window_s"])  # in the window, as the profile
    summary = {"bench": case}
    for prof in sorted(out.glob("worker-*.prof")):
        summary["profile"] = summarize(prof, stored)
        pstats.Stats(str(prof)).sort_stats("tottime").print_stats(40)
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary.get("profile"), indent=1))


if __name__ == "__main__":
    main()
