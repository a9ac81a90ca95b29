"""A cluster worker's hot path on one core, without the broker: the messages of `roadgrip bench cluster` (10 samples
of real simulated telemetry per message, one message a second per vehicle) handed to the worker's own admission and
pipeline (roadgrip/cloud/ingest/admission.py `Ingest.mqtt_message`, roadgrip/cloud/pipeline/pipeline.py `Pipeline`
with `skip_estimated`, the guarded pmf estimator) over a PostgreSQL 15 of its own, rounds run in this thread; prints
stored samples per CPU second of this process (the PostgreSQL server's CPU is not counted: it is not the worker's)
and, with --profile, where that time goes (cProfile, by cumulative and own time).

Left out, so that the figure is the parse, estimate and store path alone: AMQP delivery (pika) and the worker's
fan-out (friction topics, region messages), which `roadgrip bench cluster` includes.

    python results/trials/cluster/worker_hot_path.py --vehicles 500 --seconds 20 [--payload arrow] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import pstats
import time

from roadgrip.bench.cluster import SAMPLE_PERIOD_MS, SAMPLES_PER_MESSAGE, sample_bodies
from roadgrip.cloud.ingest.admission import Ingest
from roadgrip.cloud.pipeline.pipeline import Pipeline
from roadgrip.cloud.process import warm_up
from roadgrip.cloud.settings import Settings
from roadgrip.cloud.storage.database import open_storage
from roadgrip.cloud.storage.local_postgres import LocalPostgres
from roadgrip.estimators.learned import load_estimator


class _Sink:
    def stored(self, estimates, stored_ms, newest_data_ms) -> None:
        pass

    def tick(self, final: bool) -> None:
        pass


def messages(vehicles: int, seconds: int, payload: str, start_ms: int) -> list[list[tuple[str, bytes]]]:
    """Per second of data, one message per vehicle, encoded as the bench's load generators encode it."""
    if payload == "arrow":
        from roadgrip.cloud.ingest.wire import arrow_payload
    bodies = sample_bodies()
    rows = [[json.loads("{" + f + "}") for f in run] for run in bodies]
    out = []
    for k in range(seconds):
        second = []
        for v in range(vehicles):
            vid = f"bench{v:05d}"
            run = rows[v % len(rows)]
            samples = [
                {
                    "vehicle_id": vid,
                    "timestamp_ms": start_ms + (k * SAMPLES_PER_MESSAGE + j) * SAMPLE_PERIOD_MS,
                    **run[(k * SAMPLES_PER_MESSAGE + j) % len(run)],
                }
                for j in range(SAMPLES_PER_MESSAGE)
            ]
            body = arrow_payload(samples) if payload == "arrow" else json.dumps(samples, separators=(",", ":")).encode()
            second.append((vid, body))
        out.append(second)
    return out


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--vehicles", type=int, default=500)
    parser.add_argument("--seconds", type=int, default=20)
    parser.add_argument("--payload", choices=("json", "arrow"), default="json")
    parser.add_argument("--profile", action="store_true")
    args = parser.parse_args()
    start_ms = int(time.time() * 1000) - 86_400_000
    data = messages(args.vehicles, args.seconds, args.payload, start_ms)
    with LocalPostgres() as postgres:
        storage = open_storage(postgres.create_database("hot_path"))
        settings = Settings(database_url=storage.url, rate_limit_samples_per_s=0)
        clock = [0.0]
        estimator = load_estimator(settings.estimator)
        warm_up(estimator)  # numba's kernels compiled or loaded before the clock starts, as the worker does
        pipeline = Pipeline(storage, settings, estimator, _Sink(), True, lambda: clock[0])
        ingest = Ingest(settings, pipeline, reject=lambda vid, errors: None)
        acked = [0]

        def ack() -> None:
            acked[0] += 1

        profile = cProfile.Profile() if args.profile else None
        cpu0, wall0 = time.process_time(), time.perf_counter()
        if profile:
            profile.enable()
        for second in data:
            for vid, body in second:
                ingest.mqtt_message(vid, body, ack)
            clock[0] += 1.0
            while pipeline.backlog:
                pipeline.run_round()
        pipeline.run_round(final=True)
        if profile:
            profile.disable()
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
        stored = storage.counts()["telemetry"]
        print(
            json.dumps(
                {
                    "payload": args.payload,
                    "vehicles": args.vehicles,
                    "seconds": args.seconds,
                    "stored": stored,
                    "acked_messages": acked[0],
                    "cpu_s": round(cpu, 2),
                    "wall_s": round(wall, 2),
                    "stored_per_cpu_s": round(stored / cpu),
                    "pipeline": {k: round(v, 2) for k, v in pipeline.counters.to_dict().items() if k.endswith("_s")},
                }
            )
        )
        storage.close()
    if profile:
        stats = pstats.Stats(profile)
        stats.sort_stats("cumulative").print_stats(35)
        stats.sort_stats("tottime").print_stats(30)


if __name__ == "__main__":
    main()
