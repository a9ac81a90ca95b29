"""CPU per sample of the cloud's ingest path over a long stream, in one process, without a broker or a network: every
message goes through the service's MQTT handler (`Ingest.mqtt_message`, roadgrip/cloud/ingest/admission.py: parse, rate limit, queue), then the
pipeline (estimate, store in SQLite, map, warnings) as fast as it goes. A cost that grows with the stream's length shows
here within minutes, where the 10-minute soak of `roadgrip bench ingest` would only show the service falling behind.

Run: python results/trials/reliability/pipeline_cost.py [--vehicles 1000] [--seconds 400]   (docs/RELIABILITY.md)
Prints, every 20 s of telemetry (20 x vehicles x 10 samples): samples per wall second, CPU microseconds per sample (all
threads), the process's RSS and the estimates stored so far.
"""

import argparse
import logging
import tempfile
import time

from roadgrip.bench.ingest import _message, sample_bodies
from roadgrip.cloud.process import rss_mb, tune_memory_for_serving
from roadgrip.cloud.serve.service import CloudService
from roadgrip.cloud.settings import load_settings
from roadgrip.vehicle.params import PAPER_SUV

REPORT_EVERY_S = 20


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--vehicles", type=int, default=1000)
    parser.add_argument("--seconds", type=int, default=400, help="seconds of telemetry per vehicle")
    args = parser.parse_args()
    logging.disable(logging.WARNING)  # the warnings it raises are not the point here
    bodies = sample_bodies()
    with tempfile.TemporaryDirectory(prefix="roadgrip-cost-") as tmp:
        service = CloudService(load_settings(data_dir=tmp, mqtt="off", map_clock="data", rate_limit_samples_per_s=0))
        service.start()
        ids = [f"cost-{i:05d}" for i in range(args.vehicles)]
        service.register_vehicles([(v, PAPER_SUV) for v in ids])
        tune_memory_for_serving()  # as `roadgrip serve` does
        base_ms = int(time.time() * 1000) - args.seconds * 1000
        acked, sent = [0], 0

        def ack():
            acked[0] += 1

        wall, cpu = time.perf_counter(), time.process_time()
        for second in range(args.seconds):
            for i, vehicle in enumerate(ids):
                run = bodies[i % len(bodies)]
                lines = [
                    _message(vehicle, base_ms + (10 * second + j) * 100, run[(10 * second + j) % len(run)])
                    for j in range(10)
                ]
                service.ingest.mqtt_message(vehicle, ("[" + ",".join(lines) + "]").encode(), ack)
                sent += 1
            while acked[0] < sent - 2 * args.vehicles:  # at most two seconds of telemetry in flight
                time.sleep(0.005)
            if (second + 1) % REPORT_EVERY_S == 0:
                samples = REPORT_EVERY_S * args.vehicles * 10
                now_wall, now_cpu = time.perf_counter(), time.process_time()
                print(
                    f"{second + 1:5d} s of telemetry: {samples / (now_wall - wall):7,.0f} samples/s, "
                    f"{1e6 * (now_cpu - cpu) / samples:5.1f} us CPU a sample, RSS {rss_mb():,.0f} MB, "
                    f"{service.ingest.pipeline.counters.estimates:,} estimates",
                    flush=True,
                )
                wall, cpu = now_wall, now_cpu
        service.stop()


if __name__ == "__main__":
    main()
