"""Replay a fleet benchmark run's recorded estimates into friction maps of other settings and score them as the
benchmark does (docs/RESULTS.md, "The map").

The benchmark keeps what the service's warning engine took, round by round (DIR/estimates_seed{S}.parquet: the
estimate rows with their position and mu_proven, and the service clock of each round); the map takes the same rows in
the service (roadgrip/cloud/pipeline/fanout.py), so a map of any settings can be rebuilt from them without running the fleet
again. Each setting is scored at the benchmark's snapshots (every snapshot_every_s) against the true mu of each cell's
road, by map status (measured, bounded): MAE and 90 % coverage against the range of true mu in the cell and against its
lowest (the patch in a cell that holds one). Station reports are not replayed (the vehicles' evidence alone).

    roadgrip evaluate --benchmark fleet --out runs/fleet
    python results/trials/results/map_replay.py runs/fleet                                    # the product's map
    python results/trials/results/map_replay.py runs/fleet --set grip_locality=0.005 --set max_independent=1000
"""

from __future__ import annotations

import argparse
import ast
import collections
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

from roadgrip.cloud.domain.friction_map import BOUNDED, MEASURED, FrictionMap
from roadgrip.evaluation.fleet_benchmark import FleetConfig, make_scenario, truth_by_cell
from roadgrip.evaluation.fleet_metrics import score_cell

BANDS = ("mu<=0.2", "0.2-0.4", "0.4-0.6", "dry")


def replay_seed(run: Path, seed: int, config: FleetConfig, settings: dict) -> list[dict]:
    """Scores of every cell with evidence at every snapshot of one seed, with the map rebuilt under `settings`."""
    scenario = make_scenario(seed, config)
    table = pq.read_table(run / f"estimates_seed{seed}.parquet")
    rows = table.drop_columns(["round", "now_ms"]).to_pylist()
    for row in rows:  # the map validates mu against the interval; the recorded rows hold only the interval
        row["mu"] = 0.5 * (row["mu_lower"] + row["mu_upper"])
    rounds = table["round"].to_numpy()
    now = table["now_ms"].to_numpy()
    start_ms = int(table["timestamp_ms"].to_numpy().min()) // 1000 * 1000  # the run starts on a whole second
    instants = np.arange(config.snapshot_every_s, config.duration_s + 1.0, config.snapshot_every_s)
    fmap = FrictionMap(**settings)
    scores: list[dict] = []
    starts = np.concatenate([[0], np.flatnonzero(np.diff(rounds)) + 1, [len(rows)]])
    k = 0
    for a, b in zip(starts[:-1].tolist(), starts[1:].tolist()):
        while k < len(instants) and start_ms + instants[k] * 1000 < now[a]:
            scores += _snapshot(fmap, scenario, start_ms, float(instants[k]))
            k += 1
        fmap.add(rows[a:b], int(now[a]))
    for instant in instants[k:]:
        scores += _snapshot(fmap, scenario, start_ms, float(instant))
    return scores


def _snapshot(fmap: FrictionMap, scenario, start_ms: int, instant: float) -> list[dict]:
    truth = truth_by_cell(scenario.network, instant)
    return [
        {"status": c.status, **score_cell(c.mu, c.mu_lower, c.mu_upper, truth[c.cell])}
        for c in fmap.cells(start_ms + int(instant * 1000))
        if c.status in (MEASURED, BOUNDED) and c.cell in truth
    ]


def table(scores: list[dict]) -> str:
    groups = collections.defaultdict(list)
    for s in scores:
        groups[(s["band"], s["status"])].append(s)
    lines = [
        (
            "| band | status | cells scored | MAE (range) | 90 % coverage (range) | MAE (lowest mu) | "
            "90 % coverage (lowest mu) |"
        ),
        "| --- | --- | ---: | ---: | ---: | ---: | ---: |",
    ]
    for band in BANDS:
        for status in (MEASURED, BOUNDED):
            g = groups.get((band, status))
            if g:
                lines.append(
                    f"| {band} | {status} | {len(g)} | {np.mean([s['error'] for s in g]):.3f} | "
                    f"{np.mean([s['covered'] for s in g]):.2f} | {np.mean([s['error_low'] for s in g]):.3f} | "
                    f"{np.mean([s['covered_low'] for s in g]):.2f} |"
                )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="the --out folder of a fleet benchmark run")
    parser.add_argument("--seeds", default=None, help="comma-separated; default: every estimates_seed*.parquet there")
    parser.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="a FrictionMap argument (e.g. grip_locality=0.2); repeat for several",
    )
    args = parser.parse_args()
    settings = {}
    for item in args.set:
        name, _, value = item.partition("=")
        settings[name] = ast.literal_eval(value)
    seeds = (
        [int(s) for s in args.seeds.split(",")]
        if args.seeds
        else sorted(int(p.stem.removeprefix("estimates_seed")) for p in args.run.glob("estimates_seed*.parquet"))
    )
    if not seeds:
        raise SystemExit(f"no estimates_seed*.parquet in {args.run}: run roadgrip evaluate --benchmark fleet first")
    scores = [s for seed in seeds for s in replay_seed(args.run, seed, FleetConfig(), settings)]
    described = ", ".join(f"{k} {v}" for k, v in settings.items()) or "the product's"
    print(f"seeds {', '.join(map(str, seeds))}; map settings: {described}")
    print(table(scores))


if __name__ == "__main__":
    main()
