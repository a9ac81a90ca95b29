"""`roadgrip bench sim`: simulated seconds per wall-clock second, for one run, the paper preset and a batch of runs."""

from __future__ import annotations

import os
import platform
import time

from roadgrip.sim.presets import paper_scenarios, random_scenarios
from roadgrip.sim.simulate import simulate, simulate_truth


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            cpu = next(line.split(":", 1)[1].strip() for line in f if line.startswith("model name"))
    except (OSError, StopIteration):
        pass
    return f"{cpu}, {os.cpu_count()} logical cores, Python {platform.python_version()}, {platform.system()}"


def _timed(fn):
    start = time.perf_counter()
    fn()
    return time.perf_counter() - start


def bench_sim(batch_runs: int = 256, seed: int = 0) -> list[dict]:
    """Measure the simulator after compiling it once; returns one row per case."""
    paper = paper_scenarios(seed)
    batch = random_scenarios(batch_runs, seed)
    rows = [
        {
            "case": "first call (compiles, or loads the cached kernels)",
            "runs": 1,
            "simulated_s": paper[0].duration_s,
            "wall_s": _timed(lambda: simulate_truth(paper[:1])),
        }
    ]
    for case, scenarios, fn in (
        ("one run (paper, 40 s), dynamics only", paper[:1], simulate_truth),
        ("paper preset, 20 runs, dynamics + sensors", paper, simulate),
        (f"batch of {batch_runs} random runs, dynamics only", batch, simulate_truth),
        (f"batch of {batch_runs} random runs, dynamics + sensors", batch, simulate),
    ):
        wall = min(_timed(lambda fn=fn, scenarios=scenarios: fn(scenarios)) for _ in range(3))
        rows.append(
            {"case": case, "runs": len(scenarios), "simulated_s": sum(s.duration_s for s in scenarios), "wall_s": wall}
        )
    for row in rows:
        row["realtime_factor"] = row["simulated_s"] / row["wall_s"]
    return rows
