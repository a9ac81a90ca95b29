"""The cost of estimator state checkpoints (roadgrip/cloud/pipeline/checkpoints.py; the numbers: docs/CLOUD.md,
"Estimator state checkpoints"): encoding, storing in rounds and in one transaction, reading back and restoring a
fleet's states, each the state of one simulated production drive.
`python -m roadgrip.bench.checkpoints [--vehicles N] [--estimator pmf] [--database-url URL]` prints it as JSON.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np

from roadgrip.cloud.pipeline.checkpoints import MAX_CHECKPOINTS_PER_ROUND, Checkpoints, pack_state
from roadgrip.cloud.pipeline.pipeline import PipelineCounters
from roadgrip.cloud.storage.database import open_storage
from roadgrip.estimators.base import Estimator
from roadgrip.estimators.learned import load_estimator
from roadgrip.fleet.terminal import wire_samples
from roadgrip.sim.driver import SpeedProfile
from roadgrip.sim.production import ProductionEffects
from roadgrip.sim.roads import MuProfile
from roadgrip.sim.roads import Path as RoadPath
from roadgrip.sim.scenario import Scenario
from roadgrip.sim.simulate import simulate
from roadgrip.vehicle.params import PAPER_SUV


def _driven_state(estimator: Estimator, seconds: float, seed: int):
    """A state after `seconds` of a simulated production car (every terminal effect on) cruising and braking."""
    times = np.array([0.0, 5.0, 0.4 * seconds, 0.4 * seconds + 3.0, seconds])
    scenario = Scenario(
        run_id="checkpoint-cost",
        path=RoadPath.straight(30.0 * seconds),
        mu=MuProfile(np.array([0.0]), np.array([0.9]), np.array([0.9]), "step"),
        speed=SpeedProfile(times, np.array([15.0, 25.0, 25.0, 8.0, 20.0])),
        vehicle=PAPER_SUV,
        duration_s=seconds,
        seed=seed,
        effects=ProductionEffects.production(),
    )
    state = estimator.start(PAPER_SUV)
    for sample in wire_samples(simulate([scenario]), "car", 1_700_000_000_000):
        estimator.update(state, sample)
    return state


def measure_cost(
    vehicles: int = 1000,
    estimator_name: str = "pmf",
    database_url: str | None = None,
    seconds: float = 60.0,
    seed: int = 0,
) -> dict:
    """The cost of checkpointing `vehicles` vehicles: encoding, storing (rounds of MAX_CHECKPOINTS_PER_ROUND, and
    all in one transaction, as at a stop), reading back and restoring; the bytes of a state. Each vehicle holds the
    state of one simulated `seconds` drive (the states differ only in their vehicle_id's row)."""
    estimator = load_estimator(estimator_name)
    driven = estimator.state_to_dict(_driven_state(estimator, seconds, seed))
    with tempfile.TemporaryDirectory(prefix="roadgrip-checkpoints-") as workdir:
        url = database_url or f"sqlite:///{Path(workdir) / 'checkpoints.sqlite'}"
        storage = open_storage(url)
        try:
            ids = [f"ckpt-{k:05d}" for k in range(vehicles)]
            states = {v: estimator.state_from_dict(driven) for v in ids}
            started = time.perf_counter()
            rows = [
                {"vehicle_id": v, "estimator": estimator.name, "state": pack_state(estimator.state_to_dict(s))}
                for v, s in states.items()
            ]
            encode_s = time.perf_counter() - started
            started = time.perf_counter()
            for start in range(0, vehicles, MAX_CHECKPOINTS_PER_ROUND):
                storage.put_estimator_states(rows[start : start + MAX_CHECKPOINTS_PER_ROUND])
            rounds_s = time.perf_counter() - started
            started = time.perf_counter()
            storage.put_estimator_states(rows)
            one_transaction_s = time.perf_counter() - started
            counters = PipelineCounters()
            checkpoints = Checkpoints(storage, estimator, counters)
            started = time.perf_counter()
            restored = checkpoints.start_states({v: PAPER_SUV for v in ids})
            restore_s = time.perf_counter() - started
            if counters.checkpoints_restored != vehicles or len(restored) != vehicles:
                raise RuntimeError(f"restored {counters.checkpoints_restored} of {vehicles} states")
            database_bytes = Path(url.removeprefix("sqlite:///")).stat().st_size if database_url is None else None
        finally:
            storage.close()
    packed = len(json.dumps(rows[0]["state"]))
    return {
        "vehicles": vehicles,
        "estimator": estimator.name,
        "database": url.partition("://")[0],
        "state_bytes_packed": packed,
        "state_bytes_plain_json": len(json.dumps(driven)),
        "encode_s": round(encode_s, 4),
        "store_in_rounds_s": round(rounds_s, 4),
        "rounds": -(-vehicles // MAX_CHECKPOINTS_PER_ROUND),
        "store_one_transaction_s": round(one_transaction_s, 4),
        "read_and_restore_s": round(restore_s, 4),
        "per_vehicle_us": {
            "encode": round(encode_s / vehicles * 1e6, 1),
            "store_in_rounds": round(rounds_s / vehicles * 1e6, 1),
            "read_and_restore": round(restore_s / vehicles * 1e6, 1),
        },
        "sqlite_file_bytes": database_bytes,
    }


def main(argv: list[str] | None = None) -> None:
    """`python -m roadgrip.bench.checkpoints [--vehicles N] [--estimator pmf] [--database-url URL]`: the cost as JSON."""
    parser = argparse.ArgumentParser(prog="python -m roadgrip.bench.checkpoints", description=measure_cost.__doc__)
    parser.add_argument("--vehicles", type=int, default=1000)
    parser.add_argument("--estimator", default="pmf")
    parser.add_argument("--database-url", default=None, help="default: a temporary SQLite file")
    args = parser.parse_args(argv)
    result = measure_cost(args.vehicles, args.estimator, args.database_url)
    print(json.dumps(result, indent=2))  # a command's output


if __name__ == "__main__":
    main()
