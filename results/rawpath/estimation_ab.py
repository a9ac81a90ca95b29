"""The pipeline's estimation step both ways, in one process, passes alternated so that a shared machine's load falls on
both alike: (a) the guarded pmf's `update` sample by sample, each estimate to a dict and its cell by `cell_of` (the
pipeline before issue 27's batch step); (b) `update_many` over each vehicle's 10 samples of a round, `rows()` and
`cells_of` (the pipeline now). The cluster bench's telemetry (roadgrip/bench/cluster.py `sample_bodies`), checked by
wire.py as the worker receives it; prints the process CPU seconds of each pass and per sample, and checks that both
give the same rows.

    python results/rawpath/estimation_ab.py --vehicles 200 --seconds 20 --passes 3
    PYTHONPATH=<a checkout of main> python results/rawpath/estimation_ab.py ... --modes per_sample   (the code before)
"""

from __future__ import annotations

import argparse
import json
import time

from roadgrip.bench.cluster import SAMPLE_PERIOD_MS, SAMPLES_PER_MESSAGE, sample_bodies
from roadgrip.cloud.domain.cells import cell_of
from roadgrip.cloud.ingest.wire import parse_payload
from roadgrip.cloud.process import warm_up
from roadgrip.estimators.learned import load_estimator
from roadgrip.vehicle.params import PAPER_SUV

RESOLUTION = 11


def rounds(vehicles: int, seconds: int, start_ms: int) -> list[list[list[dict]]]:
    """Per second, per vehicle, its 10 samples as wire.py gives them."""
    runs = [[json.loads("{" + f + "}") for f in run] for run in sample_bodies()]
    out = []
    for k in range(seconds):
        second = []
        for v in range(vehicles):
            vid, run = f"bench{v:05d}", runs[v % len(runs)]
            samples = [
                {
                    "vehicle_id": vid,
                    "timestamp_ms": start_ms + (k * SAMPLES_PER_MESSAGE + j) * SAMPLE_PERIOD_MS,
                    **run[(k * SAMPLES_PER_MESSAGE + j) % len(run)],
                }
                for j in range(SAMPLES_PER_MESSAGE)
            ]
            body = json.dumps(samples).encode()
            second.append(parse_payload(body, now_ms=start_ms + 86_400_000, vehicle_id=vid)[0])
        out.append(second)
    return out


def per_sample(estimator, data) -> list[dict]:
    states = [estimator.start(PAPER_SUV) for _ in data[0]]
    rows = []
    for second in data:
        for state, samples in zip(states, second):
            for sample in samples:
                estimate = estimator.update(state, sample)
                if estimate is None:
                    continue
                row = estimate.to_dict()
                lat, lon = sample["latitude_deg"], sample["longitude_deg"]
                row["latitude_deg"], row["longitude_deg"] = lat, lon
                row["h3_cell"] = cell_of(lat, lon, RESOLUTION)
                rows.append(row)
    return rows


def per_run(estimator, data) -> list[dict]:
    from roadgrip.cloud.domain.cells import cells_of  # not in the code before issue 27's batch step

    states = [estimator.start(PAPER_SUV) for _ in data[0]]
    rows = []
    for second in data:
        for state, samples in zip(states, second):
            found = estimator.update_many(state, samples)
            judged = [samples[i] for i in found.index.tolist()]
            lats = [s["latitude_deg"] for s in judged]
            lons = [s["longitude_deg"] for s in judged]
            for row, lat, lon, cell in zip(found.rows(), lats, lons, cells_of(lats, lons, RESOLUTION)):
                row["latitude_deg"], row["longitude_deg"], row["h3_cell"] = lat, lon, cell
                rows.append(row)
    return rows


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--vehicles", type=int, default=200)
    parser.add_argument("--seconds", type=int, default=20)
    parser.add_argument("--passes", type=int, default=3)
    parser.add_argument("--modes", default="per_sample,per_run", help="per_sample alone runs on the code before too")
    args = parser.parse_args()
    data = rounds(args.vehicles, args.seconds, int(time.time() * 1000) - 86_400_000)
    n = sum(len(s) for second in data for s in second)
    estimator = load_estimator("pmf")
    warm_up(estimator)
    modes = args.modes.split(",")
    results = {name: [] for name in modes}
    reference = None
    for _ in range(args.passes):
        for name, run in (("per_sample", per_sample), ("per_run", per_run)):
            if name not in modes:
                continue
            cpu0 = time.process_time()
            rows = run(estimator, data)
            results[name].append(time.process_time() - cpu0)
            reference = reference or rows
            assert rows == reference, f"{name} gave other rows"
    print(
        json.dumps(
            {
                "samples": n,
                "estimates": len(reference),
                **{f"{name}_cpu_s": [round(t, 2) for t in times] for name, times in results.items()},
                **{f"{name}_us_per_sample_best": round(min(times) / n * 1e6, 1) for name, times in results.items()},
            }
        )
    )


if __name__ == "__main__":
    main()
